"""Published verification problems solved with the project's forms and solver (docs/verification.md)."""
