"""A strict wrapper around the CalculiX solver `ccx` (Debian package `calculix-ccx`, version 2.20).

ccx exits 0 after unknown keywords or ignored options (it only prints `*WARNING`), so a run is judged by
its log: any `*ERROR` line, or any `*WARNING` not matched by the caller's allow-list, raises
`CalculixError` together with the exit code and a timeout.  Results are read from the `.dat` file
(`*NODE PRINT` blocks): meshio cannot read `.frd` and the node prints are all the ROM analyses need.

`check_input` runs the deck with a `*NO ANALYSIS` step.  Verified on ccx 2.20: it still assembles the
element stiffness, so a nonpositive Jacobian (inverted or collapsed hex) is an `*ERROR in e_c3d`.  ccx
exits with code 201 after a `*NO ANALYSIS` step even when the deck is fine, so only the log decides.
What it cannot catch (see docs/explanation/fe-model.md, "ccx 2.20 traps met here"): anything that only fails during
solution -- a singular or underconstrained system, non-convergence under NLGEOM, a moment on a REF NODE's rotational
DOF that ccx silently ignores, ITERATIVE CHOLESKY's wrong answers, SPRINGA tables linearised in linear steps, and
memory blow-up from sparse node ids.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

CCX_DEBIAN_PACKAGE = "calculix-ccx"
#: the warning every *NO ANALYSIS run prints; harmless.
NO_ANALYSIS_WARNING = r"no analysis option was chosen"


class CalculixError(RuntimeError):
    """ccx failed: nonzero exit, an *ERROR line, an unexpected *WARNING line, or a timeout."""


@dataclass(frozen=True)
class NodePrint:
    """One block of a `.dat` file: `quantity` (e.g. 'displacements (vx,vy,vz)'), node set, step time,
    node ids (K,) and values (K, C) in the deck's units (mm, N, MPa)."""

    quantity: str
    node_set: str
    time: float
    node_ids: np.ndarray
    values: np.ndarray


@dataclass(frozen=True)
class CcxResult:
    returncode: int
    log: str
    node_prints: list[NodePrint]
    workdir: Path
    job: str
    seconds: float = 0.0  # wall time of the ccx process
    peak_rss_mb: float = 0.0  # its peak resident memory (from wait4's rusage)


def find_ccx() -> str:
    """Path of the ccx executable ($CCX, else `ccx` on PATH)."""
    exe = os.environ.get("CCX") or shutil.which("ccx")
    if not exe or not Path(exe).exists():
        raise FileNotFoundError(
            f"CalculiX solver 'ccx' not found on PATH (nor $CCX); install the Debian package "
            f"'{CCX_DEBIAN_PACKAGE}' (scripts/install_system_deps.sh) or set CCX to its path"
        )
    return exe


_HEADER = re.compile(r"^\s*(?P<quantity>\S.*?)\s+for set\s+(?P<set>\S+)\s+and time\s+(?P<time>\S+)\s*$")


def parse_dat(text: str) -> list[NodePrint]:
    """The `*NODE PRINT`-style blocks of a ccx `.dat` file (rows starting with an integer node id;
    'total' blocks, which have no ids, get node_ids = [] and their single row as values)."""
    blocks: list[NodePrint] = []
    lines = text.splitlines()
    i = 0
    while i < len(lines):
        m = _HEADER.match(lines[i])
        i += 1
        if not m:
            continue
        rows = []
        while i < len(lines) and (not lines[i].strip() or not _HEADER.match(lines[i])):
            if lines[i].strip():
                rows.append(lines[i].split())
            elif rows:
                break  # blank line after the data ends the block
            i += 1
        has_ids = (
            bool(rows)
            and rows[0][0].lstrip("-").isdigit()
            and len(rows[0]) > 1
            and "." not in rows[0][0]
            and "E" not in rows[0][0].upper()
        )
        if has_ids:
            width = len(rows[0])
            if any(len(r) != width for r in rows):
                continue  # element prints (integration points) have ragged layouts: not node prints
            table = np.array(rows, dtype=np.float64)
            ids, values = table[:, 0].astype(np.int64), table[:, 1:]
        else:
            ids = np.zeros(0, dtype=np.int64)
            values = np.array(rows, dtype=np.float64).reshape(len(rows), -1) if rows else np.zeros((0, 0))
        blocks.append(NodePrint(m["quantity"], m["set"], float(m["time"]), ids, values))
    return blocks


def log_problems(log: str, allowed_warnings: tuple[str, ...] = ()) -> list[str]:
    """Lines of a ccx log that are errors or warnings not matched by any allowed regex."""
    problems = []
    for line in log.splitlines():
        if "*ERROR" in line.upper():
            problems.append(line.strip())
        elif "*WARNING" in line.upper() and not any(re.search(p, line, re.IGNORECASE) for p in allowed_warnings):
            problems.append(line.strip())
    return problems


def exec_peak_rss_mb(pid: int, argv: list[str]) -> float:
    """Peak resident memory (MB) of process ``pid`` once it runs ``argv`` (VmHWM in /proc); 0 before its exec
    (it still shares or copies its parent's memory), once it has exited, or without /proc."""
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as f:
            cmdline = f.read().split(b"\0")[:-1]
        with open(f"/proc/{pid}/status") as f:
            hwm = next((line.split()[1] for line in f if line.startswith("VmHWM:")), None)
    except OSError:
        return 0.0
    if hwm is None or cmdline != [os.fsencode(a) for a in argv]:
        return 0.0
    return int(hwm) / 1024.0  # kB


def run_ccx(
    inp_path: str | Path,
    workdir: str | Path,
    threads: int = 1,
    timeout_s: float = 3600.0,
    allowed_warnings: tuple[str, ...] = (),
    allowed_returncodes: tuple[int, ...] = (0,),
) -> CcxResult:
    """Run `ccx -i job` on a copy of the deck in `workdir`; raise CalculixError unless the run is clean.

    threads: OMP_NUM_THREADS and CCX_NPROC_* for the run (ccx uses one CPU unless told).
    allowed_warnings: regexes for *WARNING lines that are expected; any other warning fails the run.
    Returns the exit code, the log (stdout+stderr) and the parsed `.dat` node prints.
    """
    inp_path = Path(inp_path)
    if not inp_path.is_file():
        raise ValueError(f"input deck {inp_path} does not exist")
    if threads < 1:
        raise ValueError(f"threads must be >= 1, got {threads}")
    exe = find_ccx()
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    # ccx takes the job name without suffix and chokes on spaces ("Mean_Model (Template)")
    job = re.sub(r"[^A-Za-z0-9_.-]", "_", inp_path.stem) or "job"
    target = workdir / f"{job}.inp"
    if target.resolve() != inp_path.resolve():
        shutil.copyfile(inp_path, target)
    for suffix in (".dat", ".frd", ".sta", ".cvg"):
        (workdir / f"{job}{suffix}").unlink(missing_ok=True)  # never read a previous run's results
    env = {
        **os.environ,
        "OMP_NUM_THREADS": str(threads),
        "CCX_NPROC_STIFFNESS": str(threads),
        "CCX_NPROC_EQUATION_SOLVER": str(threads),
        "CCX_NPROC_RESULTS": str(threads),
    }
    log_path = workdir / f"{job}.log"
    t0 = time.perf_counter()
    # the log goes straight to a file (a long NLGEOM run prints megabytes).  Peak memory: ccx's own high-water
    # mark, polled; wait4's ru_maxrss is at least the RSS of the process that forked it (Linux keeps the
    # pre-exec high-water mark), i.e. of this Python process, whatever ccx used
    hwm = 0.0
    with open(log_path, "w") as out:
        argv = [str(exe), "-i", job]
        proc = subprocess.Popen(argv, cwd=workdir, env=env, stdout=out, stderr=subprocess.STDOUT)
        while True:
            hwm = max(hwm, exec_peak_rss_mb(proc.pid, argv))
            pid, status, usage = os.wait4(proc.pid, os.WNOHANG)
            if pid:
                break
            if time.perf_counter() - t0 > timeout_s:
                proc.kill()
                os.wait4(proc.pid, 0)
                raise CalculixError(f"ccx on {inp_path} timed out after {timeout_s:g} s (log {log_path})")
            time.sleep(0.05)
    seconds = time.perf_counter() - t0
    returncode = os.waitstatus_to_exitcode(status)
    proc.returncode = returncode
    peak_mb = hwm if hwm > 0 else usage.ru_maxrss / 1024.0  # no /proc, or done before the first poll
    log = log_path.read_text(errors="replace")
    problems = log_problems(log, allowed_warnings)
    if returncode not in allowed_returncodes or problems:
        shown = "\n".join(problems[:20]) or log[-2000:]
        raise CalculixError(
            f"ccx on {inp_path} failed (exit code {returncode}, "
            f"{len(problems)} error/warning lines; log {log_path}):\n{shown}"
        )
    dat = workdir / f"{job}.dat"
    prints = parse_dat(dat.read_text()) if dat.exists() else []
    return CcxResult(returncode, log, prints, workdir, job, seconds, peak_mb)


_FIBRE_CARD = re.compile(
    r"^(\*MATERIAL,\s*NAME=ELASTIC_FIBER[^\n]*\n)\*USER MATERIAL,\s*CONSTANTS=\d+\s*\n"
    r"((?:[^*\n][^\n]*\n)+)",
    re.IGNORECASE | re.MULTILINE,
)


def fibre_ground_substance(model_data: str) -> str:
    """The deck with every ``ELASTIC_FIBER`` user material replaced by its ground substance
    (*HYPERELASTIC, NEO HOOKE with the same C10, D1).  ccx 2.20 crashes (segmentation fault) in a
    `*NO ANALYSIS` step as soon as an element uses the built-in fibre law, so the data check runs on the
    ground substance; the fibre law itself is exercised by the analyses that solve (spinecohort.rom.run)."""

    def repl(m):
        consts = [c for c in re.split(r"[,\s]+", m[2].strip()) if c]
        c10, d1 = float(consts[0]), float(consts[1])
        if abs(d1) < 1e-10:  # what ccx's umat_elastic_fiber itself substitutes for D1 = 0
            d1 = 1.0 / (20.0 * c10)
        return f"{m[1]}*HYPERELASTIC, NEO HOOKE\n{c10!r}, {d1!r}\n"

    return _FIBRE_CARD.sub(repl, model_data)


def check_input(
    inp_path: str | Path, workdir: str | Path, timeout_s: float = 600.0, allowed_warnings: tuple[str, ...] = ()
) -> CcxResult:
    """CalculiX data check: the deck's model data (everything before its first *STEP) plus a
    `*NO ANALYSIS` step.  Raises CalculixError on any *ERROR (e.g. a nonpositive Jacobian) or an
    unexpected *WARNING (e.g. an unknown keyword).  See the module docstring for what it cannot catch.
    ELASTIC_FIBER materials are checked as their ground substance (`fibre_ground_substance`)."""
    inp_path = Path(inp_path)
    if not inp_path.is_file():
        raise ValueError(f"input deck {inp_path} does not exist")
    text = inp_path.read_text()
    step = re.search(r"^\*STEP\b", text, re.IGNORECASE | re.MULTILINE)
    model_data = fibre_ground_substance(text[: step.start()] if step else text)
    if not model_data.endswith("\n"):
        model_data += "\n"
    workdir = Path(workdir)
    workdir.mkdir(parents=True, exist_ok=True)
    job = re.sub(r"[^A-Za-z0-9_.-]", "_", inp_path.stem) + "_check"
    deck = workdir / f"{job}.inp"
    deck.write_text(model_data + "*STEP\n*NO ANALYSIS\n*END STEP\n")
    # ccx 2.20 exits 201 after a clean *NO ANALYSIS run, so the log decides: no error lines, and the
    # run must have reached the step (an early abort would not print the analysis type)
    result = run_ccx(
        deck,
        workdir,
        timeout_s=timeout_s,
        allowed_warnings=(NO_ANALYSIS_WARNING, *allowed_warnings),
        allowed_returncodes=(0, 201),
    )
    if "No analysis was selected" not in result.log:
        raise CalculixError(f"ccx data check of {inp_path} stopped before reaching the step:\n{result.log[-2000:]}")
    return result
