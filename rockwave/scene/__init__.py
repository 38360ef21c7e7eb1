"""The scene file: its schema, validation and loading (TOML -> Scene). Nothing below this layer reads scene keys."""
