"""What made a result: the versions every run file records.

One helper for every run file (``metrics.json``, ``config.json``, ``train.json``,
``sweep.json``, ``validation.json``) and for ``torchseq --version``, so a result can be traced
to the torchseq, torch and Python that produced it, on which platform, and, when the package
runs from a git checkout, at which commit.
"""

from __future__ import annotations

import functools
import platform
import subprocess
from pathlib import Path

VERSIONS_KEY = "versions"  # the key run files hold them under (``--config`` replay skips it)


@functools.lru_cache(maxsize=1)
def _git_commit(root: Path) -> tuple[str | None, bool | None]:
    """``(commit, dirty)`` of the checkout at ``root``; ``(None, None)`` outside one."""
    if not ((root / ".git").exists() and (root / "pyproject.toml").is_file()):
        return None, None  # an installed wheel: no checkout around the package
    try:
        head = subprocess.run(["git", "-C", str(root), "rev-parse", "HEAD"],
                              capture_output=True, text=True, timeout=10)
        status = subprocess.run(["git", "-C", str(root), "status", "--porcelain",
                                 "--untracked-files=no"], capture_output=True, text=True,
                                timeout=10)
    except (OSError, subprocess.SubprocessError):  # no git on this machine
        return None, None
    if head.returncode != 0:
        return None, None
    return head.stdout.strip() or None, bool(status.stdout.strip()) if status.returncode == 0 \
        else None


def versions() -> dict[str, object]:
    """torchseq, torch, Python and platform versions, and the git commit of a checkout.

    Returns:
        ``{"torchseq", "torch", "python", "platform", "git_commit", "git_dirty"}``; the git
        entries are None when the package does not run from a git checkout (``git_dirty``:
        tracked files differ from the commit).
    """
    import torch

    import torchseq

    commit, dirty = _git_commit(Path(__file__).resolve().parents[1])
    return {"torchseq": torchseq.__version__, "torch": torch.__version__,
            "python": platform.python_version(), "platform": platform.platform(),
            "git_commit": commit, "git_dirty": dirty}


def versions_line(found: dict[str, object] | None = None) -> str:
    """One line for a console: ``torchseq 0.1.0, torch 2.13.0, Python 3.11.7, Linux-...``."""
    v = versions() if found is None else found
    line = (f"torchseq {v['torchseq']}, torch {v['torch']}, Python {v['python']}, "
            f"{v['platform']}")
    if v.get("git_commit"):
        line += f", git {str(v['git_commit'])[:12]}" + (" (modified)" if v["git_dirty"] else "")
    return line
