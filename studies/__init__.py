"""One-off parameter studies: `python -m studies <name>`, run by hand (never by `make`). See studies/README.md."""
