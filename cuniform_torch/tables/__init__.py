"""C-Uniform tables: the file (format, writer, strict reader), its content checks, and the lookup index and per-step kernels a table policy reads."""
