"""What the stages read, resolved and checked before anything is written: the bottom of ``pipeline``.

    folders    what kind of folder a path is (capture store, simulation, imported session, GEOM folder,
               ground truth, RESULT): one reader per kind, one frozen :class:`InputFolder`
    imported   an imported authors' session folder, read (``imported.json``, its stores' inventory)
    frames     the frame selection of a sequence (``--frames``)
    static     a reconstruction's inputs: capture, geometry, texture resolution
    dynamic    the dynamic stage's inputs: the dynamic capture against the static RESULT
    authors    ``polarface import-authors``: an authors' session turned into an imported session folder
"""

from polarface.pipeline.inputs.authors import (
    ImportPlan,
    ImportStoppedError,
    check_import_folder,
    check_imported_inputs,
    check_session,
    copy_unwrap_store,
    import_authors,
    prepare_imported,
)
from polarface.pipeline.inputs.dynamic import (
    check_dynamic_sequence,
    check_static_result,
    open_dynamic_capture,
    resolve_dynamic_capture,
)
from polarface.pipeline.inputs.folders import INPUT_KINDS, INPUT_READERS, InputFolder, read_input_folder
from polarface.pipeline.inputs.frames import parse_frame_selection, selection_note
from polarface.pipeline.inputs.imported import (
    IMPORTED_FORMAT,
    IMPORTED_JSON,
    IMPORTED_VERSION,
    imported_stores_problem,
    is_imported_session,
    read_imported,
)
from polarface.pipeline.inputs.static import (
    MIN_TEXTURE_RESOLUTION,
    ReconstructInputs,
    check_texture_resolution,
    max_texture_resolution,
    resolve_reconstruct_inputs,
)

__all__ = [
    "IMPORTED_FORMAT",
    "IMPORTED_JSON",
    "IMPORTED_VERSION",
    "INPUT_KINDS",
    "INPUT_READERS",
    "MIN_TEXTURE_RESOLUTION",
    "ImportPlan",
    "ImportStoppedError",
    "InputFolder",
    "ReconstructInputs",
    "check_dynamic_sequence",
    "check_import_folder",
    "check_imported_inputs",
    "check_session",
    "check_static_result",
    "check_texture_resolution",
    "copy_unwrap_store",
    "import_authors",
    "imported_stores_problem",
    "is_imported_session",
    "max_texture_resolution",
    "open_dynamic_capture",
    "parse_frame_selection",
    "prepare_imported",
    "read_imported",
    "read_input_folder",
    "resolve_dynamic_capture",
    "resolve_reconstruct_inputs",
    "selection_note",
]
