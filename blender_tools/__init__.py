"""blender_tools: see README.md."""
