"""Core types every layer shares: model definition, family registry, prepared tests, filter, metrics."""
