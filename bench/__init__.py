"""Benchmarks: ``python -m bench [--quick]`` (or ``bench/run``) runs every ``bench_*.py`` and writes
``bench/REPORT.md``. Each ``bench_*.py`` also runs alone as a plain script:
``python bench/bench_<name>.py [--quick]``.
"""
