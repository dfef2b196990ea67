"""Samplers: stratification, decorrelated lens strata, chunk-independence."""
import torch

from renderer.tracing.sampling import Sampler, permute


def test_permute_is_a_bijection_for_any_size_and_key():
    for n in (1, 2, 3, 16, 63, 64, 100, 256):
        for key in (0, 1, 12345, 2**31 + 7, 2**32 - 1):
            perm = permute(torch.arange(n), n, torch.tensor(key))
            assert sorted(perm.tolist()) == list(range(n)), f"permute(n={n}, key={key}) is not a permutation"


def test_stratified_has_one_sample_per_pixel_stratum_and_per_lens_stratum():
    spp, nx = 64, 8
    s = Sampler("stratified", spp, seed=3).pixel_samples(torch.arange(50))
    for name, cols in (("pixel", (0, 1)), ("lens", (2, 3))):
        cell = (s[..., cols[0]] * nx).long() + nx * (s[..., cols[1]] * nx).long()
        for p in range(50):
            assert torch.equal(cell[p].sort().values, torch.arange(spp)), f"{name} strata of pixel {p} not covered once"


def test_stratified_lens_strata_are_not_tied_to_pixel_strata():
    """A fixed pairing of lens and pixel strata correlates lens x with pixel x inside a pixel (the error then
    stops falling with spp); a per-pixel random permutation leaves only chance correlation (~1/sqrt(spp))."""
    for spp in (16, 64, 256):
        s = Sampler("stratified", spp).pixel_samples(torch.arange(400))
        corr = torch.stack([torch.corrcoef(torch.stack([s[p, :, 0], s[p, :, 2]]))[0, 1] for p in range(400)])
        assert corr.mean().abs() < 0.05, f"spp={spp}: mean pixel-x/lens-x correlation {corr.mean():.3f}"
        assert corr.abs().mean() < 2.0 / spp**0.5, f"spp={spp}: typical |correlation| {corr.abs().mean():.3f}"


def test_samples_do_not_depend_on_how_the_work_is_chunked():
    for name in ("independent", "stratified", "sobol"):
        smp = Sampler(name, 16, seed=1)
        whole = smp.pixel_samples(torch.arange(10))
        one_by_one = torch.stack([smp.samples(torch.full((16,), p), torch.arange(16)) for p in range(10)])
        assert torch.allclose(whole, one_by_one), f"{name}: samples differ between batched and per-sample calls"
