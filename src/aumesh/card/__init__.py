"""What a release shows: its figures, the FACS direction check, its limits and the readable model card."""
