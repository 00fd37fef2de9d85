"""Fleet analysis: many captures, analysed as `vm110 analyze` does, into one Parquet dataset
(`build`), queried with DuckDB (`query`) and summarised in one HTML page (`report`).
docs/fleet.md describes the layout and the tables."""
