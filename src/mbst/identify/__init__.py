"""Output-error identification: the fit problem, the cascade of cut-out stages."""
