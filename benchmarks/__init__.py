"""lierk's benchmarks: scripts run as ``python benchmarks/NAME.py``, or all of
them (or some) by ``python -m benchmarks [NAME ...] [--quick]`` (see
``__main__.py``).  Not part of the installed package."""
