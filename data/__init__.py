"""Package data for cpdetect: real background photographs (see backgrounds/MANIFEST.tsv)."""
