import functools
import subprocess
from pathlib import Path

__version__ = "0.1.0"


@functools.cache
def source_commit() -> str:
    """The git commit of the source tree this package runs from: ``"<sha>"``, with
    ``"+dirty"`` appended when tracked files differ from it, or ``""`` when the package
    does not run from a git checkout (an installed wheel) or git is missing. Run files
    and digests record it, and a dataset's provenance counts the runs per commit."""
    root = Path(__file__).resolve().parents[1]
    if not (root / "calendaring" / "_version.py").is_file():
        return ""

    def git(*args: str) -> str:
        return subprocess.run(["git", "-C", str(root), *args], capture_output=True,
                              text=True, timeout=10, check=True).stdout.strip()

    try:
        if Path(git("rev-parse", "--show-toplevel")).resolve() != root:
            return ""  # the package lies inside some other repository
        sha = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--untracked-files=no")
    except (OSError, subprocess.SubprocessError):
        return ""
    return sha + ("+dirty" if dirty else "")
