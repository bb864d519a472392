"""On-disk artefacts: each with one reader and one writer."""
