"""The control numerics, pure (arrays in, values out; no I/O): affine models, the condensed QP,
EPC's library, LWPR, baselines, trajectories and the cascade's ticks.
"""
