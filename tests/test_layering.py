"""The package's one-way data flow, checked on the import graph of ``src/polarface``.

A module may import from its own package and from packages in lower layers only. The order is the
README's "Layout" section; change both together.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

import polarface

#: Layers from the bottom up; packages in one layer must not import each other.
LAYERS: tuple[tuple[str, ...], ...] = (
    ("_validation", "device", "io", "executors"),  # base utilities
    ("optics",),  # physics: polarisation optics
    ("skin",),  # physics: skin model
    ("geometry",),  # data: meshes, camera, poses, ray casting, UV atlas
    ("capture",),  # data: rig, sensor, demosaicing, capture store, calibration
    ("results",),  # data: the RESULT folder
    ("texture",),  # texture-space unwrapping
    ("render",),  # the renderer
    ("simulate",),  # the rig simulator
    ("inverse",),  # inverse stages
    ("evaluate",),  # metrics of a RESULT against the simulator's ground truth
    ("export",),  # files for other tools (Mitsuba, glTF, USD, diffusion kernels)
    ("report",),  # HTML pages
    ("pipeline",),  # orchestration of stages on folders
    ("commands", "cli"),  # the command line
)

#: ``polarface.pipeline``'s rooms from the bottom up, under the same rule one level down: a stage
#: subpackage or one-command job imports only from its own room and the rooms below it.
PIPELINE_LAYERS: tuple[tuple[str, ...], ...] = (
    ("inputs",),  # what a path holds, each stage's inputs checked; the authors' import
    ("geometry",),  # the geometry stage
    ("biophysical",),  # the biophysical stage
    ("dynamic",),  # the dynamic stage (runs the geometry frames and the biophysical stage per frame)
    ("reconstruct",),  # the static reconstruction's stages (runs all of the above)
    # one-command jobs
    ("calibrate_polarization", "calibrate_rig", "export", "info", "ior", "skin_fit", "spectral_check"),
    ("calibration_check", "demo", "model_comparison"),  # jobs that simulate or reconstruct, then evaluate
)

PACKAGE_ROOT = Path(polarface.__file__).parent
LAYER_OF = {name: level for level, names in enumerate(LAYERS) for name in names}
PIPELINE_LAYER_OF = {name: level for level, names in enumerate(PIPELINE_LAYERS) for name in names}


def _top_level(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def imported_modules(source: str, module: str, is_package: bool = False) -> list[tuple[int, str]]:
    """``(line, imported module)`` of every polarface import in ``source`` (the text of ``module``),
    function-level and relative imports included."""
    package = module if is_package else module.rsplit(".", 1)[0]
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found += [(node.lineno, alias.name) for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                parts = package.split(".")
                base = parts[: len(parts) - node.level + 1]
                name = ".".join([*base, node.module] if node.module else base)
            else:
                name = node.module or ""
            found.append((node.lineno, name))
    return [(line, name) for line, name in found if name == "polarface" or name.startswith("polarface.")]


def upward_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    """The imports of ``module`` that point to its own layer's other packages or to a higher layer."""
    own = _top_level(module)
    if own not in LAYER_OF:  # polarface/__init__.py
        return []
    bad = []
    for line, name in imported_modules(source, module, is_package):
        target = _top_level(name)
        if target not in ("", own) and LAYER_OF.get(target, len(LAYERS)) >= LAYER_OF[own]:
            bad.append(f"{module}:{line} imports {name}")
    return bad


def upward_pipeline_imports(source: str, module: str, is_package: bool = False) -> list[str]:
    """The imports of a module inside ``polarface.pipeline`` that point to another room of its own
    :data:`PIPELINE_LAYERS` level, a higher room, or the ``polarface.pipeline`` face itself."""
    parts = module.split(".")
    if parts[:2] != ["polarface", "pipeline"] or len(parts) < 3:
        return []  # outside pipeline, or its face
    own = parts[2]
    bad = []
    for line, name in imported_modules(source, module, is_package):
        target = name.split(".")
        if target[:2] != ["polarface", "pipeline"]:
            continue
        room = target[2] if len(target) > 2 else ""
        if room != own and PIPELINE_LAYER_OF.get(room, len(PIPELINE_LAYERS)) >= PIPELINE_LAYER_OF[own]:
            bad.append(f"{module}:{line} imports {name}")
    return bad


def _source_files() -> list[Path]:
    return sorted(p for p in PACKAGE_ROOT.rglob("*.py") if "__pycache__" not in p.parts)


def _module_name(path: Path) -> str:
    parts = path.relative_to(PACKAGE_ROOT.parent).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def test_every_package_has_a_layer():
    top_level = {
        p.stem if p.is_file() else p.name
        for p in PACKAGE_ROOT.iterdir()
        if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem != "__init__")
    }
    assert top_level <= set(LAYER_OF), f"packages without a layer: {sorted(top_level - set(LAYER_OF))}"


def test_every_pipeline_room_has_a_layer():
    rooms = {p.stem if p.is_file() else p.name for p in (PACKAGE_ROOT / "pipeline").iterdir()
             if (p.is_dir() and (p / "__init__.py").exists()) or (p.suffix == ".py" and p.stem != "__init__")}
    assert rooms == set(PIPELINE_LAYER_OF), f"rooms without a layer: {sorted(rooms - set(PIPELINE_LAYER_OF))}"


def test_pipeline_rooms_import_downwards():
    violations = []
    for path in _source_files():
        source = path.read_text(encoding="utf-8")
        violations += upward_pipeline_imports(source, _module_name(path), path.name == "__init__.py")
    assert not violations, "imports against pipeline's rooms:\n" + "\n".join(violations)


def test_imports_point_down_the_pipeline():
    violations = []
    for path in _source_files():
        source = path.read_text(encoding="utf-8")
        violations += upward_imports(source, _module_name(path), path.name == "__init__.py")
    assert not violations, "imports against the layering:\n" + "\n".join(violations)


@pytest.mark.parametrize(
    ("source", "module", "expected"),
    [
        ("def f():\n    from polarface.commands.evaluate import x\n", "polarface.report.html", 1),
        ("import polarface.inverse\n", "polarface.optics.fresnel", 1),
        ("from ..render import shading\n", "polarface.texture.unwrap", 1),
        ("from polarface.io import device\n", "polarface.device", 1),  # same layer, other package
        ("from polarface.optics import fresnel\nfrom . import mesh\n", "polarface.geometry.camera", 0),
    ],
)
def test_the_checker_finds_upward_imports(source, module, expected):
    assert len(upward_imports(source, module)) == expected


@pytest.mark.parametrize(
    ("source", "module", "expected"),
    [
        ("from polarface.pipeline.reconstruct import reconstruct\n", "polarface.pipeline.dynamic.stage", 1),
        ("from polarface.pipeline import evaluate\n", "polarface.pipeline.inputs.static", 1),  # the face
        ("from polarface.pipeline.info import folder_info\n", "polarface.pipeline.export", 1),  # same level
        ("from polarface.pipeline.inputs import read_imported\n", "polarface.pipeline.dynamic.imported", 0),
        ("from . import config\n", "polarface.pipeline.geometry.stage", 0),
        ("from polarface.pipeline.demo import x\n", "polarface.report.html", 0),  # not pipeline's rule
    ],
)
def test_the_checker_finds_upward_pipeline_imports(source, module, expected):
    assert len(upward_pipeline_imports(source, module)) == expected
