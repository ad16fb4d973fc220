"""The ground floor: vocabulary (column names, targets, pose limits) and workspace plumbing (atomic files, signals,
provenance, this machine's settings). It imports nothing else of aumesh."""
