"""Object tracking algorithms (pure numpy; seeds 002, 003, 004)."""
