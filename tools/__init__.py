"""Command-line tools: the `pointgt` CLI, Blender scene generation, benchmarks and evaluations."""
