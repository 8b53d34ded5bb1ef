"""Light in layered skin along one dimension: Fresnel, layer stacks, the multipole diffusion,
adding-doubling totals, FFT layering, the Monte Carlo slab and its profile tables."""
