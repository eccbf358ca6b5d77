"""Maps, figures, tables and reports."""
