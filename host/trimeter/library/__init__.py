"""Named materials from repeated measurements (store, combine), their open format (format) and the
mixture check of the paper's Sec. 5.2 (mixtures)."""
