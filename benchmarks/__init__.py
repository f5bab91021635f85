"""Benchmarks of hgsloc-plugin: each module is a script, run from the repository root as
``python -m benchmarks.<name>`` (``--help`` says what it measures); ``harness.py`` holds what they share."""
