"""The project's benchmarks: performance, accuracy and robustness runs, and the generators of
the figure pages in docs/results/ (README.md is the index; `python -m benchmarks regenerate`
writes every page)."""
