"""Editing a Gaussian scene: select Gaussians (boxes, spheres, cylinders, value ranges, exclusions), move /
rotate / scale / duplicate / delete them or change their materials.

``spec.py`` parses the edit YAML, ``select.py`` evaluates selections, ``ops.py`` holds the operations,
``albedo.py`` traces the light a ``set_albedo`` selection receives, ``apply.py`` applies a named edit.
Rendering the edited scene is ``models.rendering``; scoring it against a ground truth is ``models.metrics.edits``.
"""

from .apply import apply_edit
from .ops import apply_op, selection_centre
from .select import select
from .spec import EditSpec, EditSpecError, Op, Selection, parse_edit, parse_edits, parse_selection

__all__ = ["EditSpec", "EditSpecError", "Op", "Selection", "apply_edit", "apply_op", "parse_edit", "parse_edits",
           "parse_selection", "select", "selection_centre"]
