"""ETAM: event-based tracking and mapping over zenoh."""

__version__ = "0.1.0"
