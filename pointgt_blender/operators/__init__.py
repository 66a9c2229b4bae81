"""The add-on's operators (import, proxy, rig, reset, export, device check, preview and paint transfer).

No module here imports torch at module level: the add-on registers without PyTorch."""
