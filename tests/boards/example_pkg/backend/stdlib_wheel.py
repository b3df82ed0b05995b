"""A PEP 517 build backend in the standard library alone: a pure-Python wheel of the packages beside
pyproject.toml, its metadata and entry points from the ``[project]`` table. Enough for this example package; a real
driver package would use setuptools, hatchling or flit."""

from __future__ import annotations

import base64
import hashlib
import re
import tomllib
import zipfile
from pathlib import Path

ROOT = Path.cwd()  # pip runs the backend in the project's directory


def _project() -> dict:  # type: ignore[type-arg]
    return tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]


def _dist_name(project: dict) -> str:  # type: ignore[type-arg]
    return re.sub(r"[-_.]+", "_", project["name"]).lower()


def _metadata(project: dict) -> dict[str, str]:  # type: ignore[type-arg]
    lines = ["Metadata-Version: 2.1", f"Name: {project['name']}", f"Version: {project['version']}"]
    if "description" in project:
        lines.append(f"Summary: {project['description']}")
    if "requires-python" in project:
        lines.append(f"Requires-Python: {project['requires-python']}")
    lines += [f"Requires-Dist: {dep}" for dep in project.get("dependencies", [])]
    entry_points = "".join(
        f"[{group}]\n" + "".join(f"{name} = {value}\n" for name, value in eps.items()) + "\n"
        for group, eps in project.get("entry-points", {}).items())
    wheel = "Wheel-Version: 1.0\nGenerator: stdlib_wheel\nRoot-Is-Purelib: true\nTag: py3-none-any\n"
    return {"METADATA": "\n".join(lines) + "\n", "WHEEL": wheel, "entry_points.txt": entry_points}


def get_requires_for_build_wheel(config_settings: dict | None = None) -> list[str]:  # type: ignore[type-arg]
    return []


def build_wheel(wheel_directory: str, config_settings: dict | None = None,  # type: ignore[type-arg]
                metadata_directory: str | None = None) -> str:
    project = _project()
    name = f"{_dist_name(project)}-{project['version']}"
    files = {str(p.relative_to(ROOT)): p.read_bytes()
             for pkg in sorted(ROOT.iterdir()) if (pkg / "__init__.py").is_file()
             for p in sorted(pkg.rglob("*.py"))}
    files.update({f"{name}.dist-info/{k}": v.encode() for k, v in _metadata(project).items()})
    record = [f"{path},sha256={base64.urlsafe_b64encode(hashlib.sha256(data).digest()).rstrip(b'=').decode()},"
              f"{len(data)}" for path, data in files.items()]
    files[f"{name}.dist-info/RECORD"] = ("\n".join([*record, f"{name}.dist-info/RECORD,,"]) + "\n").encode()
    wheel = f"{name}-py3-none-any.whl"
    with zipfile.ZipFile(Path(wheel_directory) / wheel, "w", zipfile.ZIP_DEFLATED) as zf:
        for path, data in files.items():
            zf.writestr(path, data)
    return wheel
