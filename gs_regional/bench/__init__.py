"""Benchmarks and checks against known answers, shared by the command lines in scripts/ and by
the tests: the truth suite (`truth/`), the sweeps (`sweeps.py`: `pareto.py`, `stability.py`,
`compactness.py`), the timings (`pipeline.py`, `parallel.py`, `scale.py`, `renderer.py`,
`export.py`, `edit.py`), the GPU checks (`gpu_checks.py`, run as the tests of tests/gpu/,
summarised by `gpu_report.py`) and `changed_gaussians.py`.

Each module with a `main(argv)` is a command line (scripts/<name>.py calls it). The runs go
through `launching.run`: a full launch.py run read back from its save/metrics.json.
"""
