"""The viser dashboard service."""
