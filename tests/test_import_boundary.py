"""The boundary of the cable, enforced: import-linter's contracts in pyproject.toml hold for the tree,
catch an import across the boundary, and name every part of the harness besides the link layer."""

from __future__ import annotations

import subprocess
import sys
import tomllib
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CONFIG = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["importlinter"]
LINT = "import sys; from importlinter.cli import lint_imports_command; sys.exit(lint_imports_command())"


def _lint(cwd: Path) -> subprocess.CompletedProcess[str]:
    env = {"PYTHONPATH": str(cwd), "PATH": "/usr/bin:/bin"}
    return subprocess.run([sys.executable, "-c", LINT], cwd=cwd, env=env, capture_output=True, text=True,
                          timeout=120)


def test_the_tree_keeps_every_contract():
    p = _lint(ROOT)
    assert p.returncode == 0, p.stdout + p.stderr
    assert f"{len(CONFIG['contracts'])} kept, 0 broken" in p.stdout


def test_an_import_across_the_cable_breaks_the_contracts(tmp_path):
    # the same contracts on a small tree where the emulator imports the onboard side and the link layer
    # imports the runner: both are reported, and lint-imports fails
    files = {
        "emulator/__init__.py": "",
        "emulator/fc.py": "import policies.pilot\n",
        "policies/__init__.py": "",
        "policies/pilot.py": "import hil.link.codec\n",
        "hil/__init__.py": "",
        "hil/link/__init__.py": "",
        "hil/link/codec.py": "from hil.runner import loop\n",
        "hil/runner/__init__.py": "",
        "hil/runner/loop.py": "import emulator.fc\nimport policies.pilot\n",
    }
    for contract in CONFIG["contracts"]:  # every module a contract names must exist
        for module in contract.get("forbidden_modules", []):
            files.setdefault(module.replace(".", "/") + "/__init__.py", "")
    for name, text in files.items():
        (tmp_path / name).parent.mkdir(parents=True, exist_ok=True)
        (tmp_path / name).write_text(text)
    (tmp_path / ".importlinter").write_text(_ini(CONFIG))
    p = _lint(tmp_path)
    assert p.returncode == 1, p.stdout + p.stderr
    assert "the emulator and the onboard side never import each other BROKEN" in p.stdout
    assert "the link layer imports neither side nor the rest of the harness BROKEN" in p.stdout
    assert "emulator.fc -> policies.pilot" in p.stdout
    assert "hil.link.codec -> hil.runner" in p.stdout


def test_the_contracts_name_every_part_of_the_harness_but_the_link_layer():
    parts = {f"hil.{p.stem}" for p in (ROOT / "hil").iterdir()
             if p.name != "__init__.py" and (p.suffix == ".py" or (p / "__init__.py").exists())}
    parts.discard("hil.link")
    by_name = {c["name"]: c for c in CONFIG["contracts"]}
    link = by_name["the link layer imports neither side nor the rest of the harness"]
    sides = by_name["both sides reach the harness only through the link layer"]
    assert set(link["forbidden_modules"]) == parts | {"emulator", "policies"}
    assert set(sides["forbidden_modules"]) == parts


def _ini(config: dict) -> str:
    """pyproject's [tool.importlinter] as the INI file lint-imports also reads."""
    lines = ["[importlinter]", "root_packages =\n    " + "\n    ".join(config["root_packages"])]
    for i, c in enumerate(config["contracts"]):
        lines.append(f"\n[importlinter:contract:{i}]")
        for key, value in c.items():
            if isinstance(value, list):
                lines.append(f"{key} =\n    " + "\n    ".join(value))
            else:
                lines.append(f"{key} = {value}")
    return "\n".join(lines) + "\n"
