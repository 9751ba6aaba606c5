"""liverforce: FE-labelled data factory and force-estimation models for robotic liver surgery."""
__version__ = "0.1.0"
