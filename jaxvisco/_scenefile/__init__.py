"""Scene files: parsing TOML scene files (materials, tables, template) into scenes and run settings."""
