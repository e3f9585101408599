"""The learned marker segmenter (HMA over HRNet-OCR, RMI loss) in plain PyTorch.

Importing this package does not import torch; its modules do.
"""
