"""A tiny random DINOv2 (2 blocks, 32 channels): the semantic stage's code paths without the
shipped weights' cost."""

import torch


def tiny_vit(seed: int = 0):
    from gsa.features.vit import DinoV2, VitConfig

    torch.manual_seed(seed)
    vit = DinoV2(VitConfig(embed_dim=32, depth=2, num_heads=2, pos_grid=16)).eval()
    with torch.no_grad():
        for p in vit.parameters():
            p.copy_(torch.randn(p.shape) * 0.3)
    return vit
