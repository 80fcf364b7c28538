"""The packages' layers, read from the source: agents (the negotiator), sim (the market and
the worlds), screener, studies, server. A package imports only the layers below it, and only
``studies`` and ``server`` may reach the screener. Every import counts, also those inside
functions and ``TYPE_CHECKING`` blocks, and so does a module named by a string for
``importlib`` (a ``"package.module"`` or ``"package.module:function"`` literal)."""

from __future__ import annotations

import ast
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("agents", "sim", "screener", "studies", "server")
FORBIDDEN = {
    "agents": {"sim", "screener", "studies", "server"},
    "sim": {"screener", "studies", "server"},
    "screener": {"studies", "server"},
    "studies": {"server"},
}
MODULE_NAME = re.compile(r"^([a-z_]+)(\.[a-z_][a-z0-9_]*)+(:[A-Za-z_][A-Za-z0-9_]*)?$")
"""A string that names a module (and maybe a function in it) for ``importlib``."""


def _resolve(module: str, level: int, name: str) -> str:
    """The absolute module of ``from <level dots><name> import ...`` inside ``module``."""
    if level == 0:
        return name
    base = module.split(".")[: len(module.split(".")) - level]
    return ".".join([*base, name] if name else base)


def imported(path: Path, root: Path = ROOT) -> list[tuple[int, str]]:
    """(line, top-level package) of every module ``path`` imports or names by string."""
    module = ".".join(path.relative_to(root).with_suffix("").parts)
    found = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            package = path.name == "__init__.py"
            where = module if package else module.rsplit(".", 1)[0] + ".x"
            found.append((node.lineno, _resolve(where, node.level, node.module or "")))
        elif (
            isinstance(node, ast.Constant)
            and isinstance(node.value, str)
            and MODULE_NAME.match(node.value)
        ):
            found.append((node.lineno, node.value.split(":")[0]))
    return sorted((line, name.split(".")[0]) for line, name in found)


def offences(package: str, root: Path = ROOT) -> list[str]:
    """``path:line imports X`` for every forbidden import of the modules under ``package``."""
    banned = FORBIDDEN[package]
    return [
        f"{path.relative_to(root)}:{line} imports {name}"
        for path in sorted((root / package).rglob("*.py"))
        for line, name in imported(path, root)
        if name in banned
    ]


@pytest.mark.parametrize("package", list(FORBIDDEN))
def test_a_package_imports_only_the_layers_below_it(package):
    assert offences(package) == []


def test_the_reader_sees_lazy_relative_and_string_imports(tmp_path):
    fake = tmp_path / "sim" / "world"
    fake.mkdir(parents=True)
    (fake / "__init__.py").write_text("")
    (fake / "mod.py").write_text(
        "from sim.market import Market\n"
        "def f():\n"
        "    import screener\n"
        "    from ..x import y\n"
        "    return 'studies.auctions:run', 'not a module', 'e.g. this'\n"
        "if False:\n"
        "    from server import app\n"
    )
    assert imported(fake / "mod.py", tmp_path) == [
        (1, "sim"),
        (3, "screener"),
        (4, "sim"),
        (5, "studies"),
        (7, "server"),
    ]
    assert offences("sim", tmp_path) == [
        "sim/world/mod.py:3 imports screener",
        "sim/world/mod.py:5 imports studies",
        "sim/world/mod.py:7 imports server",
    ]


def test_every_package_has_its_layer():
    assert {p.name for p in ROOT.iterdir() if (p / "__init__.py").is_file()} >= set(PACKAGES)
    assert set(FORBIDDEN) | {"server"} == set(PACKAGES)
