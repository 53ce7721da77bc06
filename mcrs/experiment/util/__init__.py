"""Small helpers that know nothing of a run: atomic writes, untrusted text, tables, thread counts, messages."""
