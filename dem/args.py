"""Checks of command-line arguments shared by ``dem`` and ``coupling``: each bad value is
refused with one line naming the option, before anything is read or written (the output
folder: dem.outdir.check)."""
import argparse
import math


def end_time(text):
    """argparse type of ``--end-time``: a finite number of seconds >= 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    if not math.isfinite(x) or x < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds >= 0, got {text!r}")
    return x

