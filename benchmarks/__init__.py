"""Throughput, latency and scaling figures for companion. Not tests: nothing here asserts.

Run ``python -m benchmarks.run`` (``--quick`` for a short run) from the repository root; it prints
a table and writes ``benchmarks/results.json``. See docs/performance.md.
"""
