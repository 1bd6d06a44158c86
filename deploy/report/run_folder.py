"""A run folder holds one run's outputs, never two runs' (docs/hardening.md).

``--out`` on a folder that already holds a run's outputs is refused (exit 2) unless
``--overwrite``, which removes those outputs first. Only the names a run writes are
looked at or removed: other files in the folder (a fault plan, a sweep's log) are the
user's and stay. Reusing a folder left the previous run's recording and logs beside
the new results, and an interrupted run beside an old complete metrics.json looked
like a finished run.
"""

from __future__ import annotations

import shutil
from pathlib import Path

# every name `omnifleet run` / `record` writes into its folder (deploy/report/outputs.py,
# deploy/report/figures.py, the recorder, the launcher's logs/)
FIGURE_FILES = ("fig4_trajectories.png", "fig5_errors.png", "fig6_distances_torques.png",
                "CAPTIONS.md")  # what deploy/report/figures.py writes, in this order
RECORDING = "recording.mcap"  # the run's MCAP file (deploy/report/recorder.py)
RUN_OUTPUTS = ("metrics.json", "timeseries.npz", RECORDING, "logs", *FIGURE_FILES)


class RunFolderError(ValueError):
    """The folder holds another run's outputs (exit code 2 at the CLI)."""


def previous_outputs(out: Path) -> list[str]:
    """The run outputs already in ``out`` (empty when it is fresh or missing)."""
    return [name for name in RUN_OUTPUTS if (out / name).exists()]


def prepare(out: Path, overwrite: bool) -> list[str]:
    """Make ``out`` ready for a new run: refuse a folder with another run's outputs, or
    (``overwrite``) remove them. Returns what was removed."""
    if out.exists() and not out.is_dir():
        raise RunFolderError(f"--out {out}: exists and is not a folder")
    old = previous_outputs(out)
    if old and not overwrite:
        raise RunFolderError(
            f"--out {out}: already holds a run ({', '.join(old)}); a run never mixes its "
            "outputs with another's: choose a new folder, or --overwrite to remove those first")
    for name in old:
        path = out / name
        if path.is_dir() and not path.is_symlink():
            shutil.rmtree(path)
        else:
            path.unlink()
    return old
