"""Light arriving at the skin: sampling warps, emitters, the environment map, BRDF-lobe
sampling, shadow rays on Embree and the irradiance pass."""
