"""What an engineer reads: figures, markdown pages, summary tables; family reports by name."""
