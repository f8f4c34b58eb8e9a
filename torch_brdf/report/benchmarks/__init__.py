"""The benchmarks the report runs, one module each, shipped with the package.

``python -m torch_brdf.report.benchmarks.<name> [--quick] ...`` runs one (in the repository,
``python benchmarks/<name>.py`` runs the same module); each prints progress and then one JSON
object as its last line, with its figures and, where it compares, a baseline measured in the
same run. :data:`torch_brdf.report.run.BENCHMARKS` lists them in the report's order.
:mod:`.qp_set` is not a benchmark: the held-out-like QP problems that ``inverse`` and the tests
share. ``extremes`` evaluates the test suite's cases, so it needs a source checkout.
"""
