"""Host-side simulation: cffi builds of the firmware kernel sources and helpers."""
