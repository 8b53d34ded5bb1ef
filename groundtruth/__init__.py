"""The path-traced reference: Mitsuba 3 export of the scene, rendering passes, the flat slab."""
