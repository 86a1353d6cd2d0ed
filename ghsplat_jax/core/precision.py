"""The precision every matrix product of the JAX programs asks for.

A product's default precision is the backend's: full float32 on CPUs, but TF32 (a 10-bit
mantissa) on NVIDIA GPUs since Ampere and bfloat16 passes on TPUs. The rasterizer's
transmittance sums, projections and colours must match the float64 reference to 1e-4 (the
exactness tests), and with TF32 they did not: alpha was off by 3.6e-3 on an H100 (jax 0.11.2).
So every jnp product in this package names this precision; on a CPU it changes nothing.
"""

import jax

FLOAT32 = jax.lax.Precision.HIGHEST
