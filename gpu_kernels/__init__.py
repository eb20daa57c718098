"""Array-module generic kernels: one implementation runs on CuPy with a GPU and NumPy/SciPy without."""
