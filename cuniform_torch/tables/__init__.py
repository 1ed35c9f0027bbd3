"""C-Uniform tables: the file (format, writer, strict reader), its content checks, and the lookup index and per-step kernels a table policy reads."""

from cuniform_torch.tables.file import TABLE_FORMAT, Table, TableError, read_table, write_table

__all__ = ["Table", "TableError", "read_table", "write_table", "TABLE_FORMAT"]
