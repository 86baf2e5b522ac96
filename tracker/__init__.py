"""autopose: real-time monocular 6-DoF pose tracking from an autoencoder latent (Auto-Pose)."""
__version__ = "0.1.0"
