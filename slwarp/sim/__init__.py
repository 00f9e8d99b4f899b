"""The virtual scanner: built-in rigs (rigs), scenes (scenes) and the renderer of scans with exact ground
truth (simulate)."""
