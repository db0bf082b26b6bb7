"""The package's layers (docs/design.md §7) import one way, and the optional dependencies
are imported only by what needs them."""

from __future__ import annotations

import ast
import importlib.util
import os
import subprocess
import sys
from pathlib import Path

import pytest

SRC = Path(__file__).resolve().parents[1] / "src"
#: the core's parts, lowest layer first: a part imports only itself and lower layers (the
#: top-level modules of the first layer also each other)
LAYERS = (
    ("config", "extras", "io", "lazy", "outputs", "phantoms", "pretrained"),
    ("physics",),
    ("network",),
    ("methods", "evaluation"),
    ("run", "training"),
    ("cli",),
)
LAYER = {part: rank for rank, parts in enumerate(LAYERS) for part in parts}
#: the optional or drawing-only dependencies: never imported with the core or the plugin
HEAVY = ("matplotlib", "distributed", "pytorch_msssim", "torch._dynamo")


def _imports(path: Path, package: str) -> set[str]:
    """Every module ``path`` (of the package ``package``) imports, anywhere in it."""
    found = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[: len(parts) - node.level + 1])
                module = f"{base}.{node.module}" if node.module else base
            else:
                module = node.module
            found.add(module)
            if not node.module:  # from . import part: the names are modules
                found.update(f"{module}.{alias.name}" for alias in node.names)
    return found


def _modules(package: str):
    """``(path, the package it belongs to)`` of every module of ``package`` under src/."""
    for path in sorted((SRC / package).rglob("*.py")):
        yield path, ".".join(path.relative_to(SRC).parts[:-1])


def _part(module: str) -> str | None:
    """The core part of ``svcode_core.PART...``; ``None`` for other modules."""
    parts = module.split(".")
    return parts[1] if parts[0] == "svcode_core" and len(parts) > 1 else None


def test_the_layers_are_known():
    parts = {p.stem for p in (SRC / "svcode_core").iterdir()
             if p.suffix == ".py" or (p / "__init__.py").is_file()} - {"__init__"}  # fmt: skip
    assert parts == set(LAYER)


def test_the_core_imports_one_way():
    wrong = []
    for path, package in _modules("svcode_core"):
        mine = _part(f"{package}.{path.stem}")
        for module in _imports(path, package):
            if module.split(".")[0] in ("napari_svcode", "svcode_bench"):
                wrong.append(f"{path.relative_to(SRC)} imports {module}")
            theirs = _part(module)
            if theirs not in LAYER or mine in (None, "__init__", theirs):
                continue
            if LAYER[theirs] > LAYER[mine] or (LAYER[theirs] == LAYER[mine] > 0):
                wrong.append(f"{path.relative_to(SRC)} ({mine}) imports {module}")
    assert not wrong, "\n".join(sorted(set(wrong)))


def test_the_plugin_imports_no_command_and_no_benchmark():
    wrong = [f"{path.relative_to(SRC)} imports {module}"
             for path, package in _modules("napari_svcode")
             for module in _imports(path, package)
             if module.startswith(("svcode_core.cli", "svcode_bench"))]  # fmt: skip
    assert not wrong, "\n".join(wrong)


def test_the_core_and_the_plugin_load_no_optional_dependency():
    """Importing the core, its methods and streaming, and every module of the plugin loads
    neither matplotlib (figures import it when they draw), distributed (the ``dask``
    extra), pytorch-msssim (training) nor torch's compiler (``torch._dynamo``: 2 s, loaded
    only by ``--compile``)."""
    modules = ["svcode_core", "svcode_core.methods", "svcode_core.methods.svcode",
               "svcode_core.network", "svcode_core.methods.model_file",
               "svcode_core.run.stream", "svcode_core.physics.calibration",
               "svcode_core.evaluation.metrics", "svcode_core.evaluation.figures"]  # fmt: skip
    if importlib.util.find_spec("napari") is not None:
        modules += [f"napari_svcode.{name}" for name in ("_reader", "_writer", "_sample_data",
                    "widgets.calibration", "widgets.reconstruct", "widgets.masks",
                    "widgets.simulate")]  # fmt: skip
    code = (
        "import importlib, sys\n"
        f"for name in {modules!r}:\n"
        "    importlib.import_module(name)\n"
        f"print([m for m in {HEAVY!r} if m in sys.modules])\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={**os.environ, "QT_QPA_PLATFORM": "offscreen"})  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert out.stdout.strip().splitlines()[-1] == "[]"


def test_a_missing_extra_is_named_in_one_line(monkeypatch):
    from svcode_core.extras import NotInstalled
    from svcode_core.run.parallel import dask_client

    monkeypatch.setitem(sys.modules, "distributed", None)  # as if not installed
    with pytest.raises(NotInstalled, match=r'pip install "napari-svcode\[dask\]"'):
        with dask_client(workers=1):
            pass


def test_bench_outside_a_checkout_says_how_to_get_the_engine(tmp_path):
    """Without ``bench/svcode_bench`` (an installed package, not a checkout), ``svcode
    bench --help`` still works and a run says in one line how to get the engine."""
    code = (
        "import sys\n"
        "from pathlib import Path\n"
        "sys.path = [p for p in sys.path if not p.endswith('bench')]\n"
        "import svcode_core.cli.bench as bench\n"
        f"bench.CHECKOUT_BENCH = Path({str(tmp_path)!r})\n"
        "from svcode_core.cli import main\n"
        "try:\n"
        "    main(['bench', '--help'])\n"
        "except SystemExit as done:\n"
        "    print('help', done.code)\n"
        "print(main(['bench', '--quick']))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         cwd=tmp_path)  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "usage: svcode bench" in out.stdout
    assert out.stdout.strip().splitlines()[-2:] == ["help 0", "2"]
    assert out.stderr.count("\n") == 1 and "source checkout" in out.stderr
    assert 'pip install -e ".[bench]"' in out.stderr
