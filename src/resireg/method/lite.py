"""ReSiReg Lite: every patch its own prototype, one attention step (no clustering).

Notation as :mod:`resireg.method.full` (docs/method.md#resireg-lite): intermediates ``F_v``
``[B, Dv, Hv, Wv]``, language tokens ``F_vl`` ``[B, Dl, Hl, Wl]`` and an optional segmentation
prior ``S`` ``[B, H', W']`` of instance ids (0 = none) give ``[B, Dl, Hv*s, Wv*s]`` features of
unit L2 norm over ``Dl``. Two exact computations: fused attention (``"sdpa"``) and the
factorised one from the coarse grid (:meth:`ReSiRegLite._factorised`); the grid helpers it
shares with Full are in :mod:`resireg.method.grid`.

Resolved ambiguity: the paper calls the Lite normalisation "column-wise"; we normalise
over the prototype (key) axis, the same axis as Full, so every output patch is a convex
combination of language tokens (before the optional tau gate).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from resireg.method.checks import check_variant_inputs
from resireg.method.grid import Instances, masked_mean_normalised, nearest, normalise_, upsample
from resireg.specs.variants import check_variant_kwargs

__all__ = ["ReSiRegLite", "factorised_blocks"]


# Budget for one chunk of the explicit (tau > 0) Lite attention matrix, in elements.
_LITE_CHUNK_ELEMENTS = 16 * 1024 * 1024
# Factorised Lite (ReSiRegLite._factorised), in elements: a block of queries' Gram rows
# interpolated on the query side ([queries, h w]), and a tile of their similarities to every
# key ([N, queries]). Measured on 2 cores at the protocol's size (6,912 points, one image):
# tiles of 1M, 4M, 8M, 16M elements took 0.46, 0.50, 0.49, 0.81 s on one thread, and 2.3,
# 1.4, 1.3, 1.2 s on two threads while other processes shared the cores (each elementwise
# pass is a parallel region whose barrier waits for a descheduled thread, so fewer, larger
# passes win there): 8M (32 MB in float32) is the compromise.
# The largest alpha for which the traced factorised form exponentiates alpha cos unshifted:
# exp(60) * 1e6 points * |token| stays far below float32's 3.4e38.
_GRAPH_UNSHIFTED_ALPHA = 60.0
_FACTORISED_BLOCK = 8 * 1024 * 1024
_FACTORISED_TILE = 8 * 1024 * 1024


def factorised_blocks(h: int, w: int, scale: int) -> list[tuple[int, int, int, int]]:
    """The query blocks of factorised Lite on an ``h x w`` grid upsampled by ``scale``:
    ``(r0, r1, c0, c1)``, coarse query rows ``r0:r1`` (their upsampled rows
    ``scale*r0:scale*r1``) and the coarse rows ``c0:c1`` their bilinear weights read (one
    above and one below), each block's ``[queries, h w]`` Gram rows within
    ``_FACTORISED_BLOCK`` elements (at least one coarse row)."""
    rows = max(1, _FACTORISED_BLOCK // max(1, scale * scale * w * h * w))
    return [
        (r0, min(h, r0 + rows), max(0, r0 - 1), min(h, r0 + rows + 1)) for r0 in range(0, h, rows)
    ]


def _token_index(
    lang_size: tuple[int, int], grid: tuple[int, int], scale: int, device: torch.device
) -> tuple[Tensor, bool]:
    """The language token of every point of the upsampled grid (``scale`` x ``grid``), as
    :func:`nearest` picks it (the nearest resize of the token index map, so exactly
    ``F.interpolate``'s choice): ``([N] indices into the row-major token grid, whether token
    j is the s x s block j)``, the latter when the language grid is the intermediates'."""
    (hl, wl), (h, w) = lang_size, grid
    size = (h * scale, w * scale)
    index = torch.arange(hl * wl, dtype=torch.float64, device=device).view(1, 1, hl, wl)
    token = nearest(index, size).view(-1).long()
    rows = torch.arange(size[0], device=device).div(scale, rounding_mode="floor")
    cols = torch.arange(size[1], device=device).div(scale, rounding_mode="floor")
    block = (rows.unsqueeze(1) * w + cols).view(-1)
    return token, (hl, wl) == (h, w) and torch.equal(token, block)


def _promoted(intermediates: Tensor, language: Tensor) -> tuple[Tensor, Tensor]:
    """Both inputs of the factorised form (eager and traced) in their common dtype, at least
    float32 (bfloat16 and float16 products and ``exp`` are no faster on the CPU)."""
    dtype = torch.promote_types(
        torch.promote_types(intermediates.dtype, language.dtype), torch.float32
    )
    return intermediates.to(dtype), language.to(dtype)


class ReSiRegLite(nn.Module):
    """ReSiReg Lite: every patch is its own prototype (one attention step, no clustering).

    Within each image, ``lambda_pq = softmax_q(alpha * cos(u_p, u_q))`` over the upsampled
    points (gated by ``tau``) and ``f_p = normalise(sum_q lambda_pq L_q)``, with ``u`` the
    bilinearly upsampled intermediates and ``L`` the nearest-upsampled language tokens.

    Two exact computations (docs/method.md#resireg-lite), chosen by ``attention``:

    - ``"sdpa"``: single-head attention with ``Q = K =`` the normalised upsampled points and
      ``V =`` the upsampled tokens, by ``scaled_dot_product_attention`` in O(N) memory
      (``tau = 0``; with ``tau > 0`` the gate needs explicit affinities, computed in row
      chunks so the batch's ``N x N`` never exists at once). ``4 N^2 W`` FLOP per image.
    - ``"factorised"``: both maps are linear maps of the coarse grid, so the similarities are
      the bilinear interpolation (on both sides) of the coarse Gram matrix scaled by the
      points' inverse norms, and the product with the values sums the weights of each
      nearest block and multiplies the coarse tokens (:meth:`_factorised`): about
      ``2 N h w Dl + 2 (h w)^2 Dv`` FLOP, 6.7x fewer at the protocol's size.
    - ``"auto"`` (default): ``"sdpa"`` on CUDA (fused tensor-core kernels), ``"factorised"``
      elsewhere (on the CPU it is 4-5x faster).

    A segmentation prior adds, per image, one prototype per instance (its language
    embedding is the normalised mean of the instance's tokens) with similarity 1 to the
    instance's own patches and 0 to all others, the Lite analogue of Full's prior channel
    ``d = 1 - 1[S_p = j]``: folded into the attention keys exactly in the SDPA path
    (:meth:`_with_prior`), added in closed form in the factorised one.

    Args:
        alpha: softmax temperature on cosine similarities.
        tau: gate; affinities below ``tau`` are zeroed (no renormalisation).
        upscale: integer bilinear upsampling factor ``s`` of the intermediates.
        attention: ``"auto"``, ``"sdpa"`` or ``"factorised"`` (see above).
    """

    def __init__(
        self, alpha: float = 10.0, tau: float = 0.0, upscale: int = 2, attention: str = "auto"
    ) -> None:
        super().__init__()
        # the rules of resireg.specs.variants (also those of the lite.* config checks)
        check_variant_kwargs(
            "lite", {"alpha": alpha, "tau": tau, "upscale": upscale, "attention": attention}
        )
        self.alpha, self.tau = float(alpha), float(tau)
        self.upscale = upscale
        self.attention = attention

    def extra_repr(self) -> str:
        return (
            f"alpha={self.alpha}, tau={self.tau}, upscale={self.upscale}, "
            f"attention={self.attention}"
        )

    def resolve_attention(self, device: torch.device) -> str:
        """The computation used on ``device``: ``"sdpa"`` or ``"factorised"``."""
        if self.attention != "auto":
            return self.attention
        return "sdpa" if torch.device(device).type == "cuda" else "factorised"

    @torch.no_grad()
    def forward(
        self, intermediates: Tensor, language: Tensor, prior: Tensor | None = None
    ) -> Tensor:
        """Reconstruct language features; arguments, result, errors and ``no_grad`` as
        :meth:`ReSiRegFull.forward`."""
        check_variant_inputs(intermediates, language, prior)
        dtype = torch.promote_types(intermediates.dtype, language.dtype)
        with torch.autocast(device_type=intermediates.device.type, enabled=False):
            if self.resolve_attention(intermediates.device) == "factorised":
                # traced (torch.export, the ONNX export, torch.compile): one batched graph, B N^2
                if torch.compiler.is_compiling():
                    return self._factorised_graph(intermediates, language, prior).to(language.dtype)
                return self._factorised(intermediates, language, prior).to(language.dtype)
            fv = F.normalize(upsample(intermediates.to(dtype), self.upscale), dim=1)
            b, _, h, w = fv.shape
            tokens = nearest(language.to(dtype), (h, w))
            q = fv.flatten(2).transpose(1, 2)  # [B, N, Dv]
            v = tokens.flatten(2).transpose(1, 2)  # [B, N, Dl]
            k = q
            if prior is not None:
                q, k, v = self._with_prior(q, v, prior, (h, w))
            out = self._attend(q, k, v)
            out = normalise_(out, dim=2)
        return out.transpose(1, 2).reshape(b, -1, h, w).to(language.dtype)

    def _factorised(self, intermediates: Tensor, language: Tensor, prior: Tensor | None) -> Tensor:
        """Lite from the coarse grid, exactly (docs/method.md#resireg-lite).

        Per image, with ``X`` the ``h w`` coarse points, ``U`` the bilinear upsampling and
        ``P`` the nearest one (``N x h_l w_l`` one-hot rows): the upsampled points are
        ``U X``, so their Gram matrix is ``U G U^T`` with ``G = X X^T`` (``h w x h w``), and
        ``cos(u_p, u_q) = (U G U^T)_pq r_p r_q`` with ``r = 1 / max(|U X|, 1e-12)`` per point
        (from ``up(F_v)`` itself, as ``F.normalize`` takes it). ``U G U^T`` is two bilinear
        interpolations of ``G``, one per side, so it costs a few operations per entry instead
        of a ``Dv``-long dot product. The values are ``P L``: ``E P L = (E P) L`` where
        ``E P`` sums each row's weights over the keys of one language token (an ``s x s``
        block when the grids match), so the product is with the ``h_l w_l`` coarse tokens,
        ``s^2`` times fewer rows. The softmax is taken as ``exp(alpha (cos - 1))`` (the
        largest logit is ``alpha``, the point with itself; the cosine is clamped at 1 so
        rounding cannot overflow it; computed as ``exp2``, twice as fast on the CPU) and its
        denominator is needed only for the gate, since the output is normalised.

        Work is split per image into blocks of coarse query rows (their Gram rows, from the
        rows above and below too, interpolated on the query side) and tiles of queries
        (interpolated on the key side, exponentiated, summed per block), so memory stays
        ``O(_FACTORISED_BLOCK + _FACTORISED_TILE)`` elements whatever the grid.
        Computed in at least float32 (bfloat16 and float16 inputs are promoted: on the CPU
        their products and ``exp`` are no faster). Returns ``[B, Dl, s h, s w]``.
        """
        x, lang = _promoted(intermediates, language)
        b, dv, hv, wv = x.shape
        dl, hl, wl = lang.shape[1:]
        s, alpha = self.upscale, self.alpha
        big_h, big_w = hv * s, wv * s
        n, hw = big_h * big_w, hv * wv
        dev = x.device
        token, blocks = _token_index((hl, wl), (hv, wv), s, dev)
        inst = Instances(prior, (big_h, big_w)) if prior is not None else None
        fade = math.exp(-alpha)  # an instance key's weight for a patch outside it
        # exp(alpha (cos - 1)) is taken as exp2(scale (cos - 1)): CPU exp2 is twice as fast.
        scale = alpha * math.log2(math.e)
        out = x.new_empty(b, n, dl)
        tile = max(1, _FACTORISED_TILE // n)  # queries per key-side tile
        for i in range(b):
            pts = x[i].permute(1, 2, 0).reshape(hw, dv)  # [h w, Dv] coarse points
            inv = torch.linalg.vector_norm(upsample(x[i : i + 1], s)[0], dim=0)
            inv = inv.clamp_min_(1e-12).reciprocal_().view(n, 1)  # [N, 1] r = 1 / |u_p|
            tokens = lang[i].permute(1, 2, 0).reshape(hl * wl, dl)
            extra = None
            if inst is not None:
                extra = self._prior_terms(inst, i, n, tokens[token], fade)
            for r0, r1, c0, c1 in factorised_blocks(hv, wv, s):
                gram_rows = pts[c0 * wv : c1 * wv] @ pts.T  # [(c1 - c0) w, h w]
                # Query side: U G restricted to this block's queries (channels-last, so the
                # result's rows are the queries, each a row of h w Gram entries).
                left = upsample(gram_rows.view(1, c1 - c0, wv, hw).permute(0, 3, 1, 2), s)
                q0, q1 = r0 * s * big_w, r1 * s * big_w
                left = left[0, :, s * (r0 - c0) : s * (r1 - c0)].permute(1, 2, 0).reshape(-1, hw)
                left.mul_(inv[q0:q1].mul(scale))  # the query's factor folded in: log2(e) alpha r_p
                for t0 in range(q0, q1, tile):
                    t1 = min(q1, t0 + tile)
                    side = left[t0 - q0 : t1 - q0].T.contiguous().view(1, hv, wv, t1 - t0)
                    # Key side: (U G U^T) for these queries, [N keys, queries], channels-last.
                    sim = upsample(side.permute(0, 3, 1, 2), s)[0].permute(1, 2, 0)
                    weights = sim.reshape(n, t1 - t0).mul_(inv).sub_(scale).clamp_max_(0.0).exp2_()
                    sums = self._token_sums(weights, token, blocks, (hv, wv, s), hl * wl)
                    norm = None
                    if self.tau > 0:  # gate: lambda = w / Z >= tau, then the sums again
                        norm = sums.sum(0)  # the softmax denominators [queries]
                        if extra is not None:
                            norm += extra["norm"][t0:t1]
                        weights.mul_(weights >= self.tau * norm)
                        sums = self._token_sums(weights, token, blocks, (hv, wv, s), hl * wl)
                    tile_out = out[i, t0:t1]
                    torch.mm(sums.T, tokens, out=tile_out)  # [queries, Dl]
                    if extra is not None:
                        self._add_prior(tile_out, extra, t0, t1, norm, fade)
        normalise_(out, dim=2)
        return out.transpose(1, 2).reshape(b, dl, big_h, big_w)

    def _factorised_graph(
        self, intermediates: Tensor, language: Tensor, prior: Tensor | None
    ) -> Tensor:
        """:meth:`_factorised` as one batched graph, for ``torch.export`` and the ONNX export:
        the same arithmetic without its blocks, tiles and data-dependent checks, so every shape
        is a function of the input's (dynamic batch and grid).

        Per image, the Gram matrix ``G = X X^T`` of the coarse points is bilinearly upsampled
        on the query side (``G`` read as ``h w`` channels of an ``h x w`` map), scaled by
        ``alpha r_p``, and upsampled on the key side (the queries as channels), which gives
        ``alpha cos(u_p, u_q) / r_q``; times ``r_q`` and exponentiated (shifted by ``alpha`` and
        clamped at 0 as the eager form does only where ``alpha`` > 60: unshifted, the numerators
        carry a constant factor the normalisation removes), these are the softmax numerators ``[B, N, s h, s w]``, summed over the
        keys of each language token (a sum pooling of ``s x s`` blocks when the language grid
        is the intermediates', else products with the one-hot nearest maps of rows and
        columns: the nearest resize is separable), then multiplied by the coarse tokens.
        Memory: ``B N^2`` elements at once (191 MB per image at the protocol's 6,912 points);
        the eager path keeps to :data:`_FACTORISED_BLOCK` and :data:`_FACTORISED_TILE`.
        Exported without a prior (a ValueError otherwise: its instance count is data)."""
        if prior is not None:
            raise ValueError("factorised Lite in a traced graph takes no prior")
        x, lang = _promoted(intermediates, language)
        b, dv, hv, wv = x.shape
        dl, hl, wl = lang.shape[1:]
        s, alpha = self.upscale, self.alpha
        big_h, big_w = hv * s, wv * s
        n, hw = big_h * big_w, hv * wv
        pts = x.reshape(b, dv, hw)
        gram = pts.transpose(1, 2) @ pts  # [B, h w, h w], symmetric
        inv = torch.linalg.vector_norm(upsample(x, s), dim=1).clamp_min(1e-12).reciprocal()
        inv = inv.reshape(b, 1, n)  # r_q over the keys
        # query side: [B, h w (keys), N (queries)], times alpha r_p
        left = upsample(gram.reshape(b, hw, hv, wv), s).reshape(b, hw, n) * (inv * alpha)
        # key side: [B, N (queries), s h, s w (keys)]
        sim = upsample(left.transpose(1, 2).reshape(b, n, hv, wv), s)
        logits = sim * inv.reshape(b, 1, big_h, big_w)  # alpha cos(u_p, u_q)
        if alpha <= _GRAPH_UNSHIFTED_ALPHA:  # exp(alpha cos) and its sums stay finite: the
            # shift by -alpha, a constant factor that the normalisation and the gate's
            # comparison with tau Z ignore, is left out (two passes over B N^2 fewer)
            weights = logits.exp()
        else:
            weights = (logits - alpha).clamp_max(0.0).exp()
        sums = self._graph_token_sums(weights, (hv, wv, s), (hl, wl))  # [B, N, hl wl]
        if self.tau > 0:  # gate: lambda = w / Z >= tau, then the sums again
            norm = weights.sum(dim=(2, 3), keepdim=True)
            weights = weights * (weights >= self.tau * norm).to(x.dtype)
            sums = self._graph_token_sums(weights, (hv, wv, s), (hl, wl))
        tokens = lang.reshape(b, dl, hl * wl).transpose(1, 2)  # [B, hl wl, Dl]
        out = F.normalize(sums @ tokens, dim=2)  # [B, N, Dl]
        return out.transpose(1, 2).reshape(b, dl, big_h, big_w)

    @staticmethod
    def _graph_token_sums(
        weights: Tensor, grid: tuple[int, int, int], lang_size: tuple[int, int]
    ) -> Tensor:
        """``[B, N, hl wl]``: the numerators ``weights`` ``[B, N, s h, s w]`` summed over the
        keys of each language token (:meth:`_token_sums` for :meth:`_factorised_graph`)."""
        h, w, s = grid
        hl, wl = lang_size
        b, n = weights.shape[:2]
        if (hl, wl) == (h, w):  # token j is the s x s block j
            return weights.reshape(b, n, h, s, w, s).sum(dim=(3, 5)).reshape(b, n, h * w)

        def one_hot(size: int, big: int) -> Tensor:  # [big, size]: nearest's source of each
            index = torch.arange(size, dtype=weights.dtype, device=weights.device)
            src = nearest(index.view(1, 1, 1, size), (1, big)).view(big, 1)
            return (src == index.view(1, size)).to(weights.dtype)

        cols = weights @ one_hot(wl, w * s)  # [B, N, s h, wl]
        sums = one_hot(hl, h * s).T @ cols  # [B, N, hl, wl]
        return sums.reshape(b, n, hl * wl)

    @staticmethod
    def _token_sums(
        weights: Tensor, token: Tensor, blocks: bool, grid: tuple[int, int, int], n_tokens: int
    ) -> Tensor:
        """``[n_tokens, P]``: ``sum_{q: token[q] = j} weights[q, p]`` for ``weights`` ``[N, P]``
        (keys row-major over the upsampled grid ``s h x s w``)."""
        h, w, s = grid
        p = weights.shape[1]
        if blocks:  # token j is the s x s block j: a sum pooling of the channels-last map
            grid_map = weights.view(1, h * s, w * s, p).permute(0, 3, 1, 2)
            return F.avg_pool2d(grid_map, s, divisor_override=1)[0].permute(1, 2, 0).reshape(-1, p)
        return weights.new_zeros(n_tokens, p).index_add_(0, token, weights)

    def _prior_terms(
        self, inst: Instances, image: int, n: int, values: Tensor, fade: float
    ) -> dict[str, Tensor] | None:
        """Image ``image``'s instance keys in closed form. With the logits shifted by
        ``alpha`` (as the patch weights), an instance key weighs 1 for its own patches and
        ``fade = exp(-alpha)`` for every other patch of the image, so for patch ``p`` they add
        ``fade * sum_j e_j + (1 - fade) e_(S_p)`` to the numerator and
        ``fade * m + (1 - fade) 1[S_p > 0]`` to the softmax denominator. Returns ``None``
        when the image has no instance; else ``own`` ``[N]`` (the patch's instance, -1 for
        none), ``embed`` ``[m, Dl]``, ``total`` ``[Dl]`` and ``norm`` ``[N]`` (the added
        denominator)."""
        index = inst.index[image * n : (image + 1) * n]
        mine = (inst.owner == image).nonzero().squeeze(1)
        if mine.numel() == 0:
            return None
        local = torch.full_like(index, -1)
        has = index >= 0
        local[has] = inst.local[index[has]]
        embed = masked_mean_normalised(values, local, mine.numel())  # [m, Dl]
        norm = torch.full((n,), fade * mine.numel(), dtype=values.dtype, device=values.device)
        norm[has] += 1.0 - fade
        return {"own": local, "embed": embed, "total": embed.sum(0), "norm": norm}

    def _add_prior(
        self,
        out: Tensor,
        extra: dict[str, Tensor],
        q0: int,
        q1: int,
        norm: Tensor | None,
        fade: float,
    ) -> None:
        """Add the instance keys' share (:meth:`_prior_terms`) to the numerators ``out``
        ``[q1 - q0, Dl]`` of queries ``q0:q1``, gated by ``tau`` against their softmax
        denominators ``norm``: an own instance weighs 1, the others ``fade`` each."""
        own = extra["own"][q0:q1]
        has = own >= 0
        own_embed = torch.zeros_like(out)
        own_embed[has] = extra["embed"][own[has]]
        if self.tau > 0:
            keep_own = (1.0 >= self.tau * norm).unsqueeze(1).to(out.dtype)
            keep_other = (fade >= self.tau * norm).unsqueeze(1).to(out.dtype)
        else:
            keep_own = keep_other = out.new_ones(())
        # other instances: fade * (total - own); own instance: 1 * own
        out.add_((extra["total"] - own_embed) * (fade * keep_other)).add_(own_embed * keep_own)

    def _with_prior(
        self, q: Tensor, v: Tensor, prior: Tensor, size: tuple[int, int]
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Append instance prototypes as extra keys/values, exactly.

        With ``M`` the most instances in one image, queries gain ``M`` one-hot dims (the
        patch's instance slot) and one constant dim; instance keys are one-hot in the
        slot dims, so ``q.k`` is 1 for the patch's own instance and 0 otherwise. Padding
        slots (images with fewer than ``M`` instances) get ``-1e4 / alpha`` in the constant
        dim, so ``exp(alpha * q.k)`` is exactly zero for them.
        """
        b, n, dv = q.shape
        inst = Instances(prior, size)
        m = inst.max_per_image
        if m == 0:
            return q, q, v
        dl = v.shape[2]
        embed = masked_mean_normalised(v.reshape(-1, dl).float(), inst.index, inst.count).to(
            v.dtype
        )
        inst_v = v.new_zeros(b, m, dl)
        inst_v[inst.owner, inst.local] = embed
        slot = q.new_zeros(b * n, m)
        has = inst.index >= 0
        slot[has.nonzero().squeeze(1), inst.local[inst.index[has]]] = 1.0
        slot = slot.reshape(b, n, m)
        q_aug = torch.cat([q, slot, q.new_ones(b, n, 1)], dim=2)
        k_patch = torch.cat([q, q.new_zeros(b, n, m + 1)], dim=2)
        pad = q.new_full((b, m), -1e4 / self.alpha)
        pad[inst.owner, inst.local] = 0.0
        k_inst = torch.cat(
            [
                q.new_zeros(b, m, dv),
                torch.eye(m, dtype=q.dtype, device=q.device).expand(b, m, m),
                pad.unsqueeze(2),
            ],
            dim=2,
        )
        return q_aug, torch.cat([k_patch, k_inst], dim=1), torch.cat([v, inst_v], dim=1)

    def _attend(self, q: Tensor, k: Tensor, v: Tensor) -> Tensor:
        """``softmax(alpha q k^T)`` (gated) ``@ v`` for ``[B, Nq, D]``, ``[B, Nk, D]``, ``[B, Nk, Dl]``."""
        if self.tau == 0:
            # SDPA keeps to its fused O(N)-memory kernel only for contiguous [B, 1, N, D]
            # inputs with equal q/k and v widths; otherwise it falls back to the math kernel
            # and materialises N x N (measured: 3.4 GB instead of 89 MB for 8 x 6912 points
            # with 384-d keys and 512-d values). Zero-padding the narrower side to a common
            # width changes no dot product. The width is rounded up to a multiple of 8, the
            # alignment CUDA's fused kernels need: the prior's M + 1 slot dimensions make the
            # query width arbitrary (e.g. 384 + 150 + 1).
            dl = v.shape[2]
            width = -(-max(q.shape[2], dl) // 8) * 8
            out = F.scaled_dot_product_attention(
                F.pad(q, (0, width - q.shape[2])).unsqueeze(1).contiguous(),
                F.pad(k, (0, width - k.shape[2])).unsqueeze(1).contiguous(),
                F.pad(v, (0, width - dl)).unsqueeze(1).contiguous(),
                scale=self.alpha,
            )
            return out.squeeze(1)[..., :dl]
        b, nq, _ = q.shape
        rows = max(1, _LITE_CHUNK_ELEMENTS // max(1, b * k.shape[1]))
        kt = k.transpose(1, 2)
        chunks = []
        for start in range(0, nq, rows):
            a = torch.softmax(self.alpha * (q[:, start : start + rows] @ kt), dim=2)
            a = a * (a >= self.tau)
            chunks.append(a @ v)
        return torch.cat(chunks, dim=1)
