"""Where each line looked: poses along the flight and each pixel's capture geometry (docs/layout.md)."""
