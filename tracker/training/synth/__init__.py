"""Synthetic, domain-randomised BOP scenes rendered from meshes."""
