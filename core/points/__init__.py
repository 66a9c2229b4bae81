"""points stage of the PointGT core (see core/__init__.py)."""
