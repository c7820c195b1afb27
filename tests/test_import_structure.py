"""The package's imports follow the data flow (see docs/architecture.md).

Stages, bottom to top, and what each may import::

    foundation   errors, spectral, config, io, forward_model, console, profiling, resources,
                 refdata, colour, batch, testing, metrics   → foundation only
    optics       (virtual prototype optics, plane geometry)  → foundation
    simulate     (renderer, scenes, capture sets, oracle)     → foundation, optics
    calibrate    (captures → bundle)                          → foundation, optics
    recon        (bundle + capture → cube)                    → foundation, optics
    experiments  (evaluations, the demo)                      → everything above
    viewer       (napari plugin: reader, spectrum widget)     → foundation
    commands     (cli.py, __main__, */cli_entry.py)           → anything

So reconstruction needs neither calibration nor the simulator (nor OpenCV), calibration does not
need the simulator, and nothing below the experiments imports them. Library modules import at
module level; an import inside a function of a library module carries a ``# lazy:`` comment that
says why (start-up time, an optional dependency, a cycle).
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "hsi_torch"

FOUNDATION = ("errors", "spectral", "config", "io", "forward_model", "console", "profiling",
              "resources", "refdata", "colour", "batch", "testing", "metrics")  # fmt: skip
ALLOWED = {
    "foundation": {"foundation"},
    "optics": {"foundation", "optics"},
    "simulate": {"foundation", "optics", "simulate"},
    "calibrate": {"foundation", "optics", "calibrate"},
    "recon": {"foundation", "optics", "recon"},
    "experiments": {"foundation", "optics", "simulate", "calibrate", "recon", "experiments"},
    "viewer": {"foundation", "viewer"},
}


def _module_name(path: Path) -> str:
    parts = list(path.relative_to(ROOT).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def stage_of(module: str) -> str:
    """The stage of ``hsi_torch[.x[.y]]``."""
    parts = module.split(".")
    if len(parts) == 1 or parts[1] == "__init__":
        return "foundation"  # the package root (version, lazy names)
    if parts[1] in ("cli", "__main__") or parts[-1] == "cli_entry":
        return "commands"
    if parts[1] in FOUNDATION:
        return "foundation"
    if parts[1] in ALLOWED:
        return parts[1]
    raise AssertionError(f"{module}: not assigned to a stage (add it to this test's table)")


def _imports(path: Path) -> list[tuple[str, int, bool]]:
    """``(imported module, line, inside a function)`` of every import of a file."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
    out: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, in_func: bool) -> None:
        for child in ast.iter_child_nodes(node):
            func = in_func or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if isinstance(child, ast.Import):
                out.extend((a.name, child.lineno, in_func) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                mod = child.module or ""
                if child.level:
                    base = package.split(".")
                    base = base[: len(base) - child.level + 1]
                    mod = ".".join(base + ([mod] if mod else []))
                if mod == "hsi_torch" or mod.startswith("hsi_torch."):
                    # "from hsi_torch.x import y" may import the submodule y
                    out.extend((f"{mod}.{a.name}" if _is_module(f"{mod}.{a.name}") else mod,
                                child.lineno, in_func) for a in child.names)  # fmt: skip
                else:
                    out.append((mod, child.lineno, in_func))
            visit(child, func)

    visit(tree, False)
    return out


def _is_module(name: str) -> bool:
    p = ROOT.joinpath(*name.split("."))
    return p.with_suffix(".py").is_file() or (p / "__init__.py").is_file()


def _files() -> list[Path]:
    return sorted(PKG.rglob("*.py"))


def test_every_import_follows_the_data_flow():
    bad = []
    for path in _files():
        me = _module_name(path)
        mine = stage_of(me)
        if mine == "commands":
            continue
        for mod, line, _ in _imports(path):
            if not (mod == "hsi_torch" or mod.startswith("hsi_torch.")):
                continue
            theirs = stage_of(mod)
            if theirs not in ALLOWED[mine]:
                bad.append(f"{path.relative_to(ROOT)}:{line} ({mine}) imports {mod} ({theirs})")
    assert not bad, "imports against the data flow:\n" + "\n".join(bad)


def test_no_opencv_in_reconstruction_and_the_simulator_core():
    """OpenCV (circle-grid detection, PNG masks) belongs to calibration and experiments."""
    bad = [f"{p.relative_to(ROOT)}:{line}" for p in _files()
           if stage_of(_module_name(p)) in ("recon", "optics", "foundation")
           for mod, line, in_func in _imports(p)
           if mod == "cv2" and not (in_func and "# lazy:" in _line(p, line))]  # fmt: skip
    assert not bad, "cv2 imported at module level (or without a reason) in: " + ", ".join(bad)


def _line(path: Path, line: int) -> str:
    return path.read_text(encoding="utf-8").splitlines()[line - 1]


def test_function_level_imports_state_a_reason():
    """Library modules import at module level; an import inside a function says why."""
    bad = []
    for path in _files():
        if stage_of(_module_name(path)) == "commands":
            continue
        for mod, line, in_func in _imports(path):
            if in_func and (mod == "hsi_torch" or mod.startswith("hsi_torch.")):
                if "# lazy:" not in _line(path, line):
                    bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, ("imports inside functions without a '# lazy: <reason>' comment:\n"
                     + "\n".join(bad))


def _loaded_after(code: str) -> set[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    out = subprocess.run(
        [sys.executable, "-c", code + "\nimport sys\nprint('\\n'.join(sorted(sys.modules)))"],
        env=env, capture_output=True, text=True, timeout=120, check=True,
    )  # fmt: skip
    return set(out.stdout.split())


def test_reconstruction_loads_neither_calibration_nor_opencv():
    mods = _loaded_after(
        "import hsi_torch.recon.pipeline, hsi_torch.recon.module, hsi_torch.recon.sensing, "
        "hsi_torch.recon.nnls, hsi_torch.io, hsi_torch.io.bundle"
    )
    assert "hsi_torch.recon.pipeline" in mods
    leaked = sorted(m for m in mods if m == "cv2" or m.startswith(("hsi_torch.calibrate",
                                                                    "hsi_torch.simulate",
                                                                    "hsi_torch.experiments")))
    assert not leaked, f"reconstruction loads {leaked}"


def test_the_simulator_does_not_load_calibration():
    mods = _loaded_after("import hsi_torch.simulate.capture_sets, hsi_torch.simulate.oracle")
    leaked = sorted(m for m in mods if m.startswith(("hsi_torch.calibrate", "hsi_torch.recon",
                                                      "hsi_torch.experiments")))
    assert not leaked, f"the simulator loads {leaked}"


def test_the_solver_has_one_import_path():
    """``solve_nnls`` and ``prepare_nnls`` are defined and exported once:
    ``hsi_torch.recon.nnls``."""
    exporters = []
    for path in _files():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for node in ast.walk(tree):
            if isinstance(node, ast.Assign) and any(
                isinstance(t, ast.Name) and t.id in ("__all__", "_LAZY") for t in node.targets
            ):
                names = {getattr(e, "value", None) for e in getattr(node.value, "elts", [])}
                names |= {getattr(k, "value", None) for k in getattr(node.value, "keys", [])}
                if names & {"solve_nnls", "prepare_nnls"}:
                    exporters.append(_module_name(path))
    assert sorted(exporters) == ["hsi_torch.recon.nnls", "hsi_torch.recon.nnls.problem"]
