"""buffers stage: a capture's missing buffers predicted by the buffer network (ARCHITECTURE.md)."""
