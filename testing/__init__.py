"""Test fixtures shared by the tests and the benchmarks; not part of the product.

:mod:`testing.dngwriter` writes uncompressed CFA DNG files of spectral scenes
whose every number is known (surfaces, light, camera); :mod:`testing.scenes`
draws the synthetic Mondrian scenes (one light or two) in camera RGB;
:mod:`testing.tiffs` builds linear TIFFs that declare many pixels in few bytes.
Importable from the repository root (tests, ``python -m benchmarks.NAME``);
not installed with the package.
"""
