"""``synth`` stage: synthetic captures with exact buffers rendered by Mitsuba 3 (models/synth), the ground truth
of edits, and random rooms for the buffer network (``procedural.py``)."""
