"""Whole jobs built from the stages: the demo (the main job), the speed-vs-error benchmark, batch relighting, texture
editing and glTF export. Each is a library function the CLI calls."""
