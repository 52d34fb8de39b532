"""Checks of command-line arguments shared by ``dem`` and ``coupling``: each bad value is
refused with one line naming the option, before anything is read or written."""
import argparse
import math
import os


def end_time(text):
    """argparse type of ``--end-time``: a finite number of seconds >= 0."""
    try:
        x = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"must be a number of seconds, got {text!r}") from None
    if not math.isfinite(x) or x < 0:
        raise argparse.ArgumentTypeError(f"must be a finite number of seconds >= 0, got {text!r}")
    return x


def out_dir_problem(path):
    """Why ``path`` cannot be an output folder (an existing file, a folder or parent that
    cannot be written), or None. Nothing is created."""
    if not path:
        return "is empty; give a folder"
    if os.path.exists(path) and not os.path.isdir(path):
        return f"{path} is an existing file, not a folder; give a folder path"
    probe = os.path.abspath(path)
    while not os.path.exists(probe):  # the nearest existing ancestor must let us create the rest
        parent = os.path.dirname(probe)
        if parent == probe:
            break
        probe = parent
    if not os.path.isdir(probe):
        return f"{probe} is a file, so the folder {path} cannot be created; give another path"
    if not os.access(probe, os.W_OK | os.X_OK):
        what = "folder" if probe == os.path.abspath(path) else f"parent folder {probe} of"
        return f"cannot write into the {what} {path} (permission denied); give a writable folder"
    return None
