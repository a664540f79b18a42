"""Event sources, filters, packetizer and the camera service."""
