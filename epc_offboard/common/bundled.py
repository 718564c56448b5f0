"""The files the wheel ships beside the code: default configs, scenarios, airframes.

They live in the checkout's ``config/`` (what the README, the systemd unit and other tools
name) and reach the package as ``epc_offboard/data``, a link to ``../config`` that setuptools
follows when it builds the wheel, so a checkout, an editable install and a wheel install find
the same files through :mod:`importlib.resources` and nothing reads paths relative to the
source tree.
"""

from __future__ import annotations

from importlib.resources import files
from pathlib import Path


def bundled_dir() -> Path:
    """The bundled ``config/`` folder (``default.toml``, ``sitl.toml``, ``scenarios/``,
    ``vehicles/``) as a path: an installed package is a folder on disk, never a zip."""
    data = files("epc_offboard").joinpath("data")
    if not isinstance(data, Path):  # a zipped install: processes we start need real paths
        raise RuntimeError(f"epc_offboard's bundled configs are not on disk ({data})")
    return data


def scenario_dir() -> Path:
    """The bundled scenarios (``config/scenarios``): here, not in ``tools.sim.scenario``,
    whose imports (the trajectories, numba) every CLI command's parser paid to list them."""
    return bundled_dir() / "scenarios"


def bundled_config(name_or_path: str, folder: str = "") -> Path:
    """A config given as a path, or as the name of a bundled one (``sitl``, ``default``; in
    ``folder``, e.g. ``vehicles``: ``quad_x_1500g``): ``epc-offboard run --config sitl`` works
    from any folder after a wheel install. A file that exists, or anything with a ``/`` or a
    ``.toml`` suffix, is returned as given, even when missing, so the loader's "config file
    not found" names what the user typed."""
    given = Path(name_or_path)
    if given.is_file() or "/" in name_or_path or name_or_path.endswith(".toml"):
        return given
    candidate = bundled_dir() / folder / f"{name_or_path}.toml"
    return candidate if candidate.is_file() else Path(name_or_path)


def bundled_names() -> list[str]:
    """The bundled service configs, by name (``default``, ``sitl``)."""
    return sorted(p.stem for p in bundled_dir().glob("*.toml"))
