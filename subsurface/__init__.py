"""The point-based BSSRDF (Jensen & Buhler 2002): irradiance points, octree, profile tables,
far gather, shadow edges and the sharp near field, exitance and exit radiance."""
