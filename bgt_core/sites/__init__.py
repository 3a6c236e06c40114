"""Built-in sites shipped inside the package (data files only)."""

from importlib.resources import files
from pathlib import Path


def site_dir(name: str = "tetam") -> Path:
    """Folder of a built-in site's files (tetam.dev, tetam.par, marker_positions.dat, tetam.png)."""
    path = Path(str(files(__name__) / name))
    if not path.is_dir():
        raise FileNotFoundError(f"no built-in site named {name!r}")
    return path
