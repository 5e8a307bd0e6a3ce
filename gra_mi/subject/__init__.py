"""The tracked subject: a mesh sequence with fixed topology and UVs (``sequence.npz`` + per-frame PLYs), made from the
anny body (MakeHuman-based, CC0) or a tiny procedural subject for tests."""
