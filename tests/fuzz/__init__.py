"""Fuzz targets shared by the hypothesis suite (tests/test_decoders_robust.py) and the
atheris harness (fuzz_decoders.py, not part of CI); see README.md."""
