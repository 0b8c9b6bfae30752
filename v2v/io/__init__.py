"""Output files: atomic writes, Parquet tables, summary JSON."""
