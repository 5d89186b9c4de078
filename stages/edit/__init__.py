"""Edit stage: select Gaussians (boxes, spheres, cylinders, value ranges, exclusions), move / rotate / scale /
duplicate / delete them or change their materials, render the edited scene with path-traced reflections, and
score it against the edited ground truth of a synthetic scene.

``spec.py`` parses the edit YAML, ``select.py`` evaluates selections, ``ops.py`` holds the operations,
``edit.py`` applies / renders / evaluates, ``truth.py`` renders the ground truth (synth stage).
"""

from .ops import apply_op
from .select import select
from .spec import EditSpec, EditSpecError, Op, Selection, parse_edit, parse_edits

__all__ = ["EditSpec", "EditSpecError", "Op", "Selection", "apply_op", "parse_edit", "parse_edits", "select"]
