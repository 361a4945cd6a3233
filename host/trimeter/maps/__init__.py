"""Building appearance maps and their children: the (α, σt, g) → (I_b, I_w, I_c) relation rendered once per
sample set-up (the files themselves are trimeter.formats')."""
