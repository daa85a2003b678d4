"""mapping: RGB-D datasets, ICP tracking, TSDF and surfel fusion of irradiance, colour-coherence metrics."""

from radiometry import __version__  # noqa: F401  (one version for the distribution)
