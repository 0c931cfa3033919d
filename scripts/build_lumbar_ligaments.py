"""Rebuild ``src/spinecohort/data/ligaments/remus2021_lumbar.csv``: the calibrated ligament laws of Remus et al.
2021's lumbosacral model, per segment L1-L2 ... L5-S1 and ligament group, from its repository.

Run (a second; prints the table it writes):

    git clone https://github.com/RemusR9/artisynth_lumbosacralSpineModel /tmp/remus
    python scripts/build_lumbar_ligaments.py --remus-git /tmp/remus/.git

Upstream (not vendored; BSD-3, Copyright (c) 2021, Robin Remus): per segment ``<seg>_Ligs_AS.lig`` (single-span
springs: name, spring count, summed length in m, then one line per spring: start and end point, m) and
``<seg>_Ligs_MP.lig`` (multi-point springs over the annulus: name, spring count, points per spring, then the
points, m), each with its ``*_UWMat.lig`` (name, reference strain, transition strain, linear stiffness per
spring in N per unit strain, cross-section mm^2).  The segment's own values are in its files even where the
name inside them says ``L45_``.

Steps:

1. Every spring's length: the summed length over the count (AS), the polyline's length (MP), in mm.
2. Groups: ``CL_L`` and ``CL_R`` -> ``CL``, ``ITL_L`` and ``ITL_R`` -> ``ITL`` (the two sides' springs pooled;
   their laws are equal); the other names as they are.
3. One row per segment and group: the springs' count, their mean length (mm), the reference strain, the
   transition strain and the linear stiffness per spring (N per unit strain), as upstream.  The law they define
   (rest length = geometric length x (1 + reference strain), a quadratic toe up to the transition strain, then
   linear) is `spinecohort.fe.ligament_curves`.
"""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

import numpy as np
import pandas as pd

GEOMETRY = "hybrid_LSS_model/src/artisynth/models/passiveComponents_PlosOne/geometry"
SEGMENTS = {"L12": "L1-L2", "L23": "L2-L3", "L34": "L3-L4", "L45": "L4-L5", "L51": "L5-S1"}
OUT = Path(__file__).resolve().parents[1] / "src" / "spinecohort" / "data" / "ligaments" / "remus2021_lumbar.csv"


def show(git_dir: Path, path: str) -> str:
    return subprocess.run(
        ["git", "--git-dir", str(git_dir), "show", f"HEAD:{GEOMETRY}/{path}"],
        check=True,
        capture_output=True,
        text=True,
    ).stdout


def spring_lengths(text: str, multipoint: bool) -> dict[str, np.ndarray]:
    """Ligament name -> its springs' lengths (mm) from a ``.lig`` geometry file."""
    lines = [ln.strip() for ln in text.strip().splitlines() if ln.strip()]
    out, i = {}, 1  # line 0: the number of ligaments
    while i < len(lines):
        head = [h.strip() for h in lines[i].split(",")]
        name, count = head[0].split("_", 1)[1], int(head[1])
        rows = lines[i + 1 : i + 1 + count]
        if multipoint:
            pts = [
                np.array([float(v) for v in r.replace("\t", ",").split(",") if v.strip()]).reshape(-1, 3) for r in rows
            ]
            out[name] = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in pts]) * 1e3
        else:
            ends = np.array([[float(v) for v in r.split(",")] for r in rows])
            out[name] = np.linalg.norm(ends[:, 3:] - ends[:, :3], axis=1) * 1e3
        i += 1 + count
    return out


def laws(text: str) -> dict[str, tuple[float, float, float]]:
    """Ligament name -> (reference strain, transition strain, linear stiffness N per unit strain)."""
    out = {}
    for ln in text.strip().splitlines()[1:]:
        parts = [p.strip() for p in ln.split(",")]
        if len(parts) >= 4:
            out[parts[0].split("_", 1)[1]] = (float(parts[1]), float(parts[2]), float(parts[3]))
    return out


def table(git_dir: Path) -> pd.DataFrame:
    rows = []
    for key, segment in SEGMENTS.items():
        for kind, multipoint in (("AS", False), ("MP", True)):
            lengths = spring_lengths(show(git_dir, f"{key}_Ligs_{kind}.lig"), multipoint)
            law = laws(show(git_dir, f"{key}_Ligs_{kind}_UWMat.lig"))
            groups: dict[str, list[str]] = {}
            for name in lengths:
                groups.setdefault(name.split("_")[0], []).append(name)
            for group, names in groups.items():
                values = {law[n] for n in names}
                if len(values) != 1:
                    raise ValueError(f"{segment} {group}: the sides' laws differ: {values}")
                eps_r, eps_t, k = values.pop()
                springs = np.concatenate([lengths[n] for n in names])
                rows.append(
                    {
                        "segment": segment,
                        "group": group,
                        "springs": len(springs),
                        "mean_length_mm": round(float(springs.mean()), 3),
                        "reference_strain": eps_r,
                        "transition_strain": eps_t,
                        "stiffness_n_per_spring": k,
                    }
                )
    return pd.DataFrame(rows).sort_values(["segment", "group"], kind="stable").reset_index(drop=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--remus-git", type=Path, required=True, help="git directory of the Remus repository")
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args()
    df = table(a.remus_git)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    df.to_csv(a.out, index=False)
    print(df.to_string(index=False))
    print(f"-> {a.out} ({len(df)} rows)")


if __name__ == "__main__":
    main()
