"""Stage 1 of the data flow: multi-view images and their cameras (NeRF-synthetic layout), rays."""
