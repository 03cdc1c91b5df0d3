"""``splatreplace``: command-line tools around the splat-replace nerfstudio method."""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from typing import Union

# nerfstudio's camera utilities use torch.jit.script, which torch now deprecates: a warning on every command
# (``--help`` included) that the user can do nothing about
warnings.filterwarnings("ignore", message=r".*torch\.jit\.script.*deprecated", category=FutureWarning)

import tyro
from typing_extensions import Annotated

from splatreplace_ns.tools.bench.capture import BenchCaptureConfig
from splatreplace_ns.tools.bench.mask_passes import BenchMaskPassesConfig
from splatreplace_ns.tools.bench.masks import BenchMasksConfig
from splatreplace_ns.tools.bench.register import BenchRegisterConfig
from splatreplace_ns.tools.bench.render import BenchRenderConfig
from splatreplace_ns.tools.bench.scale import BenchScaleConfig
from splatreplace_ns.tools.bench.segment import BenchSegmentConfig
from splatreplace_ns.tools.bench.template import BenchTemplateConfig
from splatreplace_ns.tools.bench.tradeoff import BenchTradeoffConfig
from splatreplace_ns.tools.bench.sim import BenchSimConfig
from splatreplace_ns.tools.bench.suite import BenchSuiteConfig
from splatreplace_ns.tools.demo import DemoCommand
from splatreplace_ns.export import ExportCommand
from splatreplace_ns.method.masks_command import MasksCommand
from splatreplace_ns.tools.sim import SimCommand
from splatreplace_ns.user_errors import error_lines, user_error_types

BenchCommands = Union[
    Annotated[BenchRenderConfig, tyro.conf.subcommand("render")],
    Annotated[BenchSimConfig, tyro.conf.subcommand("sim")],
    Annotated[BenchSegmentConfig, tyro.conf.subcommand("segment")],
    Annotated[BenchTemplateConfig, tyro.conf.subcommand("template")],
    Annotated[BenchRegisterConfig, tyro.conf.subcommand("register")],
    Annotated[BenchMasksConfig, tyro.conf.subcommand("masks")],
    Annotated[BenchMaskPassesConfig, tyro.conf.subcommand("mask-passes")],
    Annotated[BenchTradeoffConfig, tyro.conf.subcommand("tradeoff")],
    Annotated[BenchSuiteConfig, tyro.conf.subcommand("suite")],
    Annotated[BenchCaptureConfig, tyro.conf.subcommand("capture")],
    Annotated[BenchScaleConfig, tyro.conf.subcommand("scale")],
]


@dataclass
class BenchCommand:
    """Benchmarks: print a table and write JSON (machine, versions, wall time beside accuracy)."""

    which: tyro.conf.OmitArgPrefixes[BenchCommands]

    def main(self) -> None:
        self.which.main()


Commands = Union[
    Annotated[SimCommand, tyro.conf.subcommand("sim", description="Write a synthetic repetitive scene with ground truth.")],
    Annotated[DemoCommand, tyro.conf.subcommand("demo", description="Run the method on the embedded default scene.")],
    Annotated[ExportCommand, tyro.conf.subcommand("export", description="Export the replaced scene (3DGS PLY + instanced file).")],
    Annotated[MasksCommand, tyro.conf.subcommand("masks", description="Instance masks for a capture from one click per instance.")],
    Annotated[BenchCommand, tyro.conf.subcommand("bench")],
]


def entrypoint() -> None:
    command = tyro.cli(tyro.conf.OmitSubcommandPrefixes[Commands])
    try:
        command.main()
    except user_error_types() as err:
        print(error_lines(err), file=sys.stderr)
        raise SystemExit(2) from None


if __name__ == "__main__":
    entrypoint()
