"""The camera's sensor as a setup describes it: one pydantic model of the pixel grid for Part I, II and III.

:class:`CameraGridSpec` is the base of every setup's camera table. It turns the grid fields into the one pixel
convention, :class:`scopetwin.scenes.camera.PixelGrid` (:meth:`CameraGridSpec.grid`), and writes it to a dict
(:meth:`CameraGridSpec.grid_dict`, the keys of :meth:`scopetwin.scenes.camera.PixelGrid.as_dict`). Each setup keeps the
TOML
keys its presets and files already use and adds what is its own:

* Part I (:class:`scopetwin.scenes.setup.CameraSpec`): ``pixels = [nx, ny]``, ``pixel_pitch`` (mm) and ``r_cs`` (the
  keys
  the calibration writes back), plus the pose of §1.6.2 / §2.5.2, distortion and thin lens;
* Part II and III (:class:`PixelGridSpec`: ``width_px``, ``height_px``, ``pixel_um``): the CMU's Basler
  scA1400-30gm with its bit depth (§4.1.4, :class:`scopetwin.scenes.cmu.layout.CmuCameraSpec`) and the AVT Guppy behind
  the GRIN objectives (§8.4.3, :class:`scopetwin.scenes.grin.setup.GrinCameraSpec`).

The pitch is kept in the unit the file gives and converted once, in :meth:`CameraGridSpec.grid_fields` (a mm <-> µm
round trip is not exact in floating point: 6.5 µm -> 0.0065 mm -> 6.500000000000001 µm).
"""

from __future__ import annotations

from typing import Annotated, Any

from pydantic import BaseModel, ConfigDict, Field

from scopetwin.scenes.camera import PixelGrid

PositiveInt = Annotated[int, Field(gt=0)]
Positive = Annotated[float, Field(gt=0, ge=1e-9, le=1e9)]  # finite and in a physical range


class CameraGridSpec(BaseModel):
    """Base of the setups' camera tables: the pixel grid, its one conversion to a PixelGrid and to a dict."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)

    def grid_fields(self) -> tuple[int, int, float, tuple[float, float]]:
        """(nx, ny, pitch in mm, r_cs in mm) of this camera, from the fields as its setup spells them."""
        raise NotImplementedError

    def grid(self) -> PixelGrid:
        """The camera's pixel grid: the pixel <-> sensor convention of :class:`scopetwin.scenes.camera.PixelGrid`."""
        nx, ny, pitch, r_cs = self.grid_fields()
        return PixelGrid(int(nx), int(ny), float(pitch), r_cs)

    @property
    def pitch_mm(self) -> float:
        """Pixel pitch, mm."""
        return self.grid_fields()[2]

    def grid_dict(self) -> dict[str, Any]:
        """JSON-ready grid (``nx``, ``ny``, ``pitch`` in mm, ``r_cs``):
        :meth:`scopetwin.scenes.camera.PixelGrid.as_dict`."""
        return self.grid().as_dict()


class PixelGridSpec(CameraGridSpec):
    """A camera's sensor: ``width_px`` x ``height_px`` square pixels of ``pixel_um`` (the Part II and III keys).

    Subclasses set the defaults of their camera and may add fields (the CMU camera's bit depth).
    """

    width_px: PositiveInt
    height_px: PositiveInt
    pixel_um: Annotated[float, Field(ge=0.1, le=1000.0)]  # 0.1 µm to 1 mm

    def grid_fields(self) -> tuple[int, int, float, tuple[float, float]]:
        """(width_px, height_px, pixel_um * 1e-3, centred on the axis)."""
        return self.width_px, self.height_px, self.pixel_um * 1e-3, (0.0, 0.0)
