"""Quality of 8-node hexahedra (C3D8) for a batch of morphed models.

- `element`: the hex's node order (VTK = Verdict = Abaqus/CalculiX C3D8), edges, faces, shape-function tables.
- `verdict`: the per-element metrics in numpy (Verdict/VTK definitions), the reference implementation.
- `kernels`: the same metrics compiled with numba, per mesh and per batch of models (what the pipeline runs).
- `certificate`: exact validity (det J > 0 everywhere inside) by Bernstein coefficients and subdivision.
- `table3`: the seed's Table 3 per part and per model, and the shard pass's one-pass check.
"""
