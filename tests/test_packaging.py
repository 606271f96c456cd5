"""Packaging: every package is installed under daof.*, the configs ship with it, nothing shadows a user's modules."""

import subprocess
import sys
from pathlib import Path

import tomllib

ROOT = Path(__file__).resolve().parents[1]


def _declared() -> tuple[list[str], dict[str, str]]:
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    return tool["packages"], tool["package-dir"]


def test_every_package_folder_is_declared_under_the_daof_namespace():
    packages, dirs = _declared()
    found = set()
    for top, name in (("daof", "daof"), ("envs", "daof.envs"), ("losses", "daof.losses")):
        for init in (ROOT / top).rglob("__init__.py"):
            rel = init.parent.relative_to(ROOT / top).parts
            found.add(".".join((name, *rel)))
    assert found == set(packages), f"pyproject.toml's packages differ from the folders: {found ^ set(packages)}"
    assert all(p == "daof" or p.startswith("daof.") for p in packages)
    assert dirs == {"daof.envs": "envs", "daof.losses": "losses"}


def test_installed_daof_does_not_shadow_top_level_envs_or_losses(tmp_path):
    """A user's own ``envs`` package wins: daof installs nothing at the top level but ``daof``."""
    (tmp_path / "envs").mkdir()
    (tmp_path / "envs" / "__init__.py").write_text("MINE = True\n")
    code = "import envs, daof.envs, daof.losses; assert envs.MINE; print(daof.envs.make_system('linear').name)"
    out = subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip() == "linear"


def test_training_configs_ship_inside_the_package():
    import daof.train.config as config

    assert config.CONF_DIR == ROOT / "daof" / "conf"
    for group in ("filter", "system", "tuning"):
        assert list((config.CONF_DIR / group).glob("*.yaml")), group
