"""Local illumination models of skin, each one unit that owns its parameters, kernels and docs
(docs/software.md "Models")."""
