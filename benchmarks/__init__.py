"""Benchmarks and paper reproductions: tools for developing the product, not part of it.

Each module runs as ``python -m benchmarks.NAME`` from the repository root
(docs/benchmarks.md lists them). They use the product packages
(``models``, ``recovery``, ``service``) and the fixtures of :mod:`testing`;
no product module imports them. Not installed with the package; their extra
dependencies are the ``[bench]`` extra.
"""
