"""forensics: what an image sensor leaves in its images."""
__version__ = "0.1.0"
