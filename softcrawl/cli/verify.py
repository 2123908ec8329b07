"""``softcrawl verify``: placeholder wired below once the checks exist."""
