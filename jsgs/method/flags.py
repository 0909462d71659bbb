"""The ``jsgs train`` switches of ``--method jsgs``, each setting one of its ``method_options`` (reached
through the method registry, :func:`jsgs.train.method.method_flags`; the command line adds them to
``jsgs train`` and refuses them with another method)."""

from __future__ import annotations

from jsgs.train.method import MethodFlag

FLAGS: tuple[MethodFlag, ...] = (
    MethodFlag(
        "--jpeg-mode",
        "jpeg_mode",
        "forward of the JPEG observation operator (method_options.jpeg_mode) [default: paper].",
        choices=("exact", "paper", "float"),
    ),
    MethodFlag(
        "--tables",
        "tables",
        "the quantization JO and DS use (method_options.tables): the files' header tables, or the effective "
        "tables of views compressed twice (needs `jsgstools manifest --analyze`) [default: header].",
        choices=("header", "effective"),
    ),
    MethodFlag(
        "--compile",
        "speed.compile",
        "torch.compile JO, L_obs and DS (method_options.speed.compile) [default: off].",
        choices=("off", "inductor", "aot_eager"),
    ),
    MethodFlag("--no-jo", "jo", "no JPEG observation operator (needs --no-ds --no-gc).", value=False),
    MethodFlag("--no-ds", "ds", "no DCT supervision (L_low, L_mid).", value=False),
    MethodFlag("--no-gc", "gc", "no Gaussian Controller (L_fro).", value=False),
)
