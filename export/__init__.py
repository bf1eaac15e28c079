"""Per-stage ONNX export of D3LVO (completion, encoder, flow+pose), checks, manifest and parity."""
