"""Export a calibrated model to other tools' formats (calibrated URDF)."""

from .urdf import UrdfComparison, UrdfExport, compare_urdf, constant_origins, export_urdf, urdf_only_model

__all__ = ["UrdfComparison", "UrdfExport", "compare_urdf", "constant_origins", "export_urdf", "urdf_only_model"]
