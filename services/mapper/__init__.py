"""Mapper: semi-dense 3D maps from events and camera poses (seed 001's EMVS space sweep)."""
