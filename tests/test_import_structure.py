"""The package's imports follow the data flow (see docs/architecture.md).

Stages, bottom to top, and what each may import::

    foundation   errors, spectral, bayer, config, io, forward_model, console, profiling,
                 resources, refdata, colour, metrics, cli_common, provenance, devices,
                 findings
                 → foundation only
    optics       (virtual prototype optics, plane geometry)  → foundation, but not io
    simulate     (renderer, scenes, capture sets, oracle)     → foundation, optics
    calibrate    (captures → bundle)                          → foundation, optics
    recon        (bundle + capture → cube)                    → foundation, optics
    experiments  (evaluations, the demo)                      → everything above
    viewer       (napari plugin: reader, spectrum widget)     → foundation
    commands     (cli.py, __main__, */cli_entry.py)           → anything, but nothing imports cli

So reconstruction needs neither calibration nor the simulator (nor OpenCV), calibration does not
need the simulator, and nothing below the experiments imports them. The optics are physics with no
file I/O (the Bayer mosaic they and the readers share is the foundation's ``bayer``). The command
line reaches the ``*/cli_entry.py`` modules by name and they take what they share from
``cli_common``, so no module imports ``cli`` back (only ``__main__`` runs it). Inside the
reconstruction, the run layer (``recon.batch``: the driver loop, output targets, tasks) sits on
top: the reconstructor, the module and the solvers never import it; Dask is imported only by
``recon.distributed``; the settings and the configuration schema load without the
reconstructor. Library modules import at module level; an import inside a function of a library
module carries a ``# lazy:`` comment that says why (start-up time, an optional dependency).
"""

from __future__ import annotations

import ast
import os
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PKG = ROOT / "hsi_torch"

FOUNDATION = ("errors", "spectral", "bayer", "config", "io", "forward_model", "console",
              "profiling", "resources", "refdata", "colour", "metrics",
              "cli_common", "provenance", "devices", "findings")  # fmt: skip
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


def _imports(path: Path, type_checking: bool = True) -> list[tuple[str, int, bool]]:
    """``(imported module, line, inside a function)`` of every import of a file
    (``type_checking=False``: without those under ``if TYPE_CHECKING:``, never run)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rsplit(".", 1)[0]
    out: list[tuple[str, int, bool]] = []

    def visit(node: ast.AST, in_func: bool) -> None:
        for child in ast.iter_child_nodes(node):
            if not type_checking and isinstance(child, ast.If) and \
                    "TYPE_CHECKING" in ast.unparse(child.test):
                continue
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


def test_the_optics_do_no_file_io():
    """The device's physics reads and writes no files: nothing in ``optics`` imports ``io``."""
    bad = [f"{p.relative_to(ROOT)}:{line} imports {mod}" for p in _files()
           if stage_of(_module_name(p)) == "optics"
           for mod, line, _ in _imports(p)
           if mod == "hsi_torch.io" or mod.startswith("hsi_torch.io.")]  # fmt: skip
    assert not bad, "optics import hsi_torch.io:\n" + "\n".join(bad)


def test_nothing_imports_the_command_line_back():
    """``cli`` calls the entry functions by name; they (and everything else) never import it."""
    bad = [f"{p.relative_to(ROOT)}:{line}" for p in _files()
           if _module_name(p) != "hsi_torch.__main__"
           for mod, line, _ in _imports(p)
           if mod == "hsi_torch.cli"]  # fmt: skip
    assert not bad, "modules importing hsi_torch.cli: " + ", ".join(bad)


def test_no_import_cycle_between_errors_and_config():
    """``errors`` is the bottom of the package: it imports nothing from ``hsi_torch``."""
    mods = [m for m, _, _ in _imports(PKG / "errors.py")]
    assert not [m for m in mods if m.startswith("hsi_torch")], mods


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
    # the module's compiler-disabled methods import torch's compiler on first use only
    # (it costs about 70 MiB and a second that a process reconstructing files never needs)
    assert "torch._dynamo" not in mods and "sympy" not in mods


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


def test_the_run_layer_sits_on_top_of_the_reconstruction():
    """``recon.batch`` (driver, targets, tasks, entry) may import the reconstruction; nothing
    else of the reconstruction imports it (only the commands and the experiments may)."""
    bad = []
    for path in _files():
        me = _module_name(path)
        if stage_of(me) != "recon" or me.startswith("hsi_torch.recon.batch"):
            continue
        for mod, line, _ in _imports(path):
            if mod.startswith("hsi_torch.recon.batch"):
                bad.append(f"{path.relative_to(ROOT)}:{line} imports {mod}")
    assert not bad, "the reconstruction imports its run layer:\n" + "\n".join(bad)


def test_dask_is_imported_only_by_the_distributed_module():
    bad = [f"{p.relative_to(ROOT)}:{line}" for p in _files()
           for mod, line, _ in _imports(p)
           if mod.split(".")[0] in ("dask", "distributed")
           and _module_name(p) != "hsi_torch.recon.distributed"]  # fmt: skip
    assert not bad, "dask imported outside hsi_torch.recon.distributed: " + ", ".join(bad)
    mods = _loaded_after("import hsi_torch.recon.batch.entry, hsi_torch.recon.cli_entry")
    assert "hsi_torch.recon.distributed" in mods
    assert not {"dask", "distributed"} & mods, "a serial run's modules load Dask"


def test_the_settings_and_the_config_load_without_the_reconstructor():
    mods = _loaded_after("import hsi_torch.recon.settings, hsi_torch.recon.config")
    assert "hsi_torch.recon.settings" in mods
    leaked = sorted(m for m in mods if m.startswith("hsi_torch.recon.")
                    and m not in ("hsi_torch.recon.settings", "hsi_torch.recon.config"))
    assert not leaked, f"the settings load {leaked}"


def test_numba_is_imported_in_one_place():
    """numba is optional: only ``hsi_torch.recon._numba`` imports it (availability, the
    ``HSI_TORCH_NO_NUMBA`` switch, thread counts); the kernels take it from there."""
    bad = [f"{p.relative_to(ROOT)}:{line}" for p in _files()
           if _module_name(p) != "hsi_torch.recon._numba"
           for mod, line, _ in _imports(p) if mod == "numba" or mod.startswith("numba.")]
    assert not bad, "numba imported outside hsi_torch/recon/_numba.py: " + ", ".join(bad)


def test_the_solver_rules_are_defined_once():
    """The exchange rules of the active-set solver (the ¼·tol threshold, Murty's counter, the
    zero-set/free-set switch at M // 2, the compiled kernel's floor) appear as numbers only in
    ``hsi_torch/recon/nnls/constants.py``; the torch and the compiled kernels import them."""
    bad = []
    for path in sorted((PKG / "recon" / "nnls").glob("*.py")):
        if path.name == "constants.py":
            continue
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, ast.Constant) and node.value in (0.25, 1e-300):
                bad.append(f"{path.name}:{node.lineno} literal {node.value}")
            if (isinstance(node, ast.BinOp) and isinstance(node.op, ast.FloorDiv)
                    and isinstance(node.right, ast.Constant) and node.right.value == 2):
                bad.append(f"{path.name}:{node.lineno} '// 2'")
            if (isinstance(node, ast.Assign) and any(getattr(t, "id", "") == "backup"
                                                     for t in node.targets)
                    and isinstance(node.value, ast.Constant)):
                bad.append(f"{path.name}:{node.lineno} Murty's counter as a literal")
    assert not bad, "solver rules written outside nnls/constants.py: " + ", ".join(bad)
    from hsi_torch.recon.nnls import _compiled, active_set, constants, frame  # noqa: F401

    assert constants.MURTY_PATIENCE == 3 and constants.INFEASIBILITY_FRACTION == 0.25
    assert constants.zero_set_limit(25) == 12


def test_the_spatial_admm_loop_is_written_once():
    """One ADMM loop and stopping rule in ``recon/spatial/admm.py`` for every backend: the
    residuals are compared with the tolerance in one function, and no module of the package
    but it iterates over ``CHECK_EVERY`` (or the loop's ``check_every`` argument)."""
    spatial = PKG / "recon" / "spatial"
    hits = []
    for path in sorted(spatial.glob("*.py")):
        text = path.read_text(encoding="utf-8")
        hits += [f"{path.name}:{i + 1}" for i, ln in enumerate(text.splitlines())
                 if "range(check_every)" in ln.lower() or "prim <= tol" in ln]
    assert len(hits) == 2 and all(h.startswith("admm.py:") for h in hits), hits


def _import_graph() -> dict[str, set[str]]:
    """Package module → the package modules it imports (module level and inside functions, not
    the type checker's ``if TYPE_CHECKING:`` imports; a package's own name stands for its
    ``__init__``)."""
    graph: dict[str, set[str]] = {}
    for path in _files():
        me = _module_name(path)
        graph[me] = {mod for mod, _, _ in _imports(path, type_checking=False)
                     if (mod == "hsi_torch" or mod.startswith("hsi_torch.")) and mod != me
                     and _is_module(mod)}  # fmt: skip
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_the_import_graph_has_no_cycle():
    """No module imports (directly or through others) a module that imports it back, counting
    the imports inside functions too: each module can be read, tested and changed from the
    bottom up."""
    graph = _import_graph()
    assert "hsi_torch.recon.sensing" in graph["hsi_torch.recon.pipeline"]  # the graph is read
    cycles = _cycles(graph)
    assert not cycles, "import cycles:\n" + "\n".join(" <-> ".join(c) for c in cycles)


def test_the_cycle_finder_finds_a_cycle():
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []
