"""Statistics: :mod:`.lda` (linear discriminant analysis), :mod:`.bootstrap` (cluster bootstrap)."""
