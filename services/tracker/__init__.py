"""Object tracking and camera ego-motion."""
