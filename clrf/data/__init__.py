"""Dataset loaders: Blender synthetic, tiny .npz, LLFF, instant-ngp transforms.json, procedural."""
