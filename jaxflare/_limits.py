"""Stated maxima of the render's counts, in one place (the scenes validate them, the command line
parses against them; plain Python, importable without JAX)."""

MAX_SAMPLES = 2**32
"""The most Monte Carlo samples one render draws (64 x the production budget of 2^26)."""
MAX_SEED = 2**32 - 1
"""Seeds are 0 .. 2^32 - 1 (JAX's PRNG keys take 32-bit seeds on every platform)."""
MAX_RESOLUTION = 16384
"""The most pixels per side of a render."""
