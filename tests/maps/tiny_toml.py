"""A tiny recipe as TOML text, for tests that write it to a file (build CLIs, the pipeline)."""


def tiny_toml(name: str) -> str:
    return f"""
name = "{name}"
geometry = "ideal"
n = 1.5
thickness_mm = 0.5
[grid]
alpha = {{ max = 0.99, count = 5 }}
sigma_t = [0.5, 5.0]
g = [0.0, 0.5]
[sampling]
target_stderr = 1.0
min_paths = 4096
max_paths = 4096
"""
