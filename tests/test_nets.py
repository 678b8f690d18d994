"""The networks' channels-last fc layouts compute PyTorch's plain (C, H, W) formulation."""

import torch
import torch.nn.functional as F

from shared.nets import Decoder, Encoder

OBS_SHAPE = (9, 84, 84)


def plain_encoder(encoder: Encoder, obs: torch.Tensor) -> torch.Tensor:
    h = encoder.convs(obs.float().contiguous()).flatten(1)  # NCHW, flattened (C, H, W)
    return torch.tanh(encoder.ln(encoder.fc(h)))


def plain_decoder(decoder: Decoder, z: torch.Tensor) -> torch.Tensor:
    h = F.relu(decoder.fc(z)).view(-1, *decoder.conv_shape)
    return torch.sigmoid(decoder.deconvs(h.contiguous()))


def grads(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    out = {name: p.grad.clone() for name, p in module.named_parameters()}
    module.zero_grad()
    return out


def test_encoder_and_decoder_match_the_plain_layout_in_values_and_gradients():
    torch.manual_seed(0)
    encoder = Encoder(OBS_SHAPE, 50).to(memory_format=torch.channels_last)
    decoder = Decoder(OBS_SHAPE, encoder.conv_shape, 50).to(memory_format=torch.channels_last)
    for module in (encoder, decoder):  # break the init's symmetries, so a wrong permutation shows
        for p in module.parameters():
            p.data.add_(0.05 * torch.randn_like(p))
    obs = torch.randint(0, 256, (4, *OBS_SHAPE), dtype=torch.uint8)
    target = torch.rand(4, *OBS_SHAPE)

    ours = decoder(encoder(obs))
    F.mse_loss(ours, target).backward()
    ours_grads = grads(encoder) | {f"dec.{k}": v for k, v in grads(decoder).items()}

    plain = plain_decoder(decoder, plain_encoder(encoder, obs))
    F.mse_loss(plain, target).backward()
    plain_grads = grads(encoder) | {f"dec.{k}": v for k, v in grads(decoder).items()}

    torch.testing.assert_close(ours, plain, rtol=1e-5, atol=1e-6)
    assert ours_grads.keys() == plain_grads.keys()
    for name in plain_grads:
        torch.testing.assert_close(ours_grads[name], plain_grads[name], rtol=1e-4, atol=1e-7, msg=name)

