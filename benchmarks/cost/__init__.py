"""What each heat-transfer mechanism costs on the shared settled bed (see run.py)."""
