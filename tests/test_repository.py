"""The repository's own rules: a short front door, nothing that points outside the project,
every setting documented."""

from __future__ import annotations

import re
import tomllib
from pathlib import Path

from packaging.requirements import Requirement

from server.config import Settings

ROOT = Path(__file__).resolve().parents[1]
README_LINES = 200
OUTSIDE = re.compile(r"\.\./shared|shared/specs|DECISIONS\.md|INTERFACE\.md|STYLE\.md|spec §")
"""What would point at the authors' inputs kept outside the project."""


def project_files() -> list[Path]:
    roots = ("agents", "sim", "screener", "studies", "server", "tests", "benchmarks", "examples")
    roots += ("docs",)
    found = [ROOT / "README.md", ROOT / "pyproject.toml", ROOT / "Dockerfile", ROOT / "Makefile"]
    for root in roots:
        found += [p for p in (ROOT / root).rglob("*") if p.suffix in (".py", ".md", ".toml")]
    return [p for p in found if p.is_file() and p != Path(__file__)]


def test_the_readme_is_a_short_front_door() -> None:
    lines = (ROOT / "README.md").read_text().splitlines()
    assert len(lines) <= README_LINES
    for link in re.findall(r"\]\((docs/[^)#]+)", "\n".join(lines)):
        assert (ROOT / link).exists(), link


def test_nothing_refers_to_files_outside_the_project() -> None:
    offenders = [
        f"{path.relative_to(ROOT)}:{n}"
        for path in project_files()
        for n, line in enumerate(path.read_text(errors="replace").splitlines(), 1)
        if OUTSIDE.search(line)
    ]
    assert offenders == []


def test_every_setting_is_documented() -> None:
    page = (ROOT / "docs" / "server.md").read_text()
    for name in Settings.model_fields:
        assert f"SRD_{name.upper()}" in page, name


def _name(requirement: str) -> str:
    """A requirement's project name, normalised (PEP 503)."""
    name = re.split(r"[\s\[<>=!~;@]", requirement.strip(), maxsplit=1)[0]
    return re.sub(r"[-_.]+", "-", name).lower()


def test_every_dependency_is_pinned_by_the_lock() -> None:
    """``constraints.txt`` pins every dependency ``make install`` installs (torch is pinned in
    the Makefile and the Dockerfile), each at a version its own requirement accepts."""
    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    wanted = list(project["dependencies"])
    for extra in ("dev", "ray"):
        wanted += project["optional-dependencies"][extra]
    pins: dict[str, str] = {}
    for line in (ROOT / "constraints.txt").read_text().splitlines():
        if line and not line.startswith("#"):
            name, _, version = line.partition("==")
            assert version, f"constraints.txt: {line!r} is not name==version"
            pins[_name(name)] = version
    for requirement in wanted:
        requirement = requirement.split(";")[0].strip()
        name = _name(requirement)
        if name == "torch":
            continue
        assert name in pins, f"{name} is not in constraints.txt (make lock)"
        assert Requirement(requirement).specifier.contains(pins[name]), (requirement, pins[name])
