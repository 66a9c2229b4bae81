"""The "PointGT" render engine and Composite with Scene (the PointGT layer merged with Cycles/EEVEE)."""
