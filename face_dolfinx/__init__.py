"""face_dolfinx: facial muscle activations from motion capture on a FEniCSx face model."""
