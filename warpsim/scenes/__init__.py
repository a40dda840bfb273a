"""Scene presets for the command line."""
