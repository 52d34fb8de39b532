"""Work-precision benchmarks of the DEM and thermal settings (see run.py)."""
