"""The application layer: the `vio` commands, replay, the onboard daemon and `vio status`.

This is the only code in `vio` that may import `drivers` and `calib`; the core (everything else in `vio`)
imports neither, nor this package (tests/test_layering.py enforces it). Entry point: `vio.app.cli:main`.
"""
