"""The instrument's forward model: material (α, σt, g) + sample (n, ℓ) + backgrounds → (I_b, I_w, I_c)."""
