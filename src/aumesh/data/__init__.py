"""py-feat's files read as they are: layouts, units, cleaning, the data contract, a video's clip."""
