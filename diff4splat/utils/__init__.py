"""The package's utilities below everything else: argument checks, limits, devices, errors, constants, the
shipped config files, measured costs, weight offloading and numba's settings."""
