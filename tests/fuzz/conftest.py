# The atheris harness is a script, never a test module (it needs atheris and runs forever).
collect_ignore = ["fuzz_decoders.py"]
