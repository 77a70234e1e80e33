"""Pages generated at build time."""
