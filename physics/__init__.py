"""Host physics shared by several stages: Fresnel and diffusion closed forms, layer stacks and
presets, lights and their sampling, visibility, colour.  Kernel-side physics lives in ``cl/``."""
