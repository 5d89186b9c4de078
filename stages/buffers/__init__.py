"""``buffers`` stage: a capture's missing buffers predicted by the buffer network (models/buffernet/fill.py)."""
