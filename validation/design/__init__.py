"""Rig design studies (run as ``python -m validation.design.NAME``)."""
