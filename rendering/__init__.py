"""From camera to pixels: camera rays and hits, the per-pixel surface pass, shading a model's
kernel over the pixel samples, colour encoding."""
