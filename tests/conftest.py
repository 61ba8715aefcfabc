"""Test configuration: float64 is enabled so references and float64 kernel paths can be checked;
float32 paths are exercised by passing float32 arrays explicitly."""

import jax

jax.config.update("jax_enable_x64", True)
