"""System identification (N4SID), shared by the applications."""
