"""Buffer-network training stage (ARCHITECTURE.md: buffernet-train)."""
