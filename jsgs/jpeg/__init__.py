"""JPEG math shared by the toolkit and the trainer: quantization tables, the observation operator (JO) and the
DCT-domain supervision (DS). Tables are always 8x8 in natural row-major order, indexed [v, u] (row = vertical
frequency), as Pillow >= 8.3 returns them."""
