"""Studies of the diagnose verb (run as ``python -m validation.diagnose.NAME``)."""
