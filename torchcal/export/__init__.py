"""Export a calibrated model to other tools' formats (calibrated URDF, controller compensation tables)."""

from .controller import (
    export_tables,
    read_linuxcnc_comp,
    read_tables_csv,
    write_linuxcnc_comp,
    write_siemens_cec,
    write_tables_csv,
)
from .urdf import (
    UrdfComparison,
    UrdfExport,
    compare_urdf,
    constant_origins,
    export_urdf,
    urdf_only_model,
)

__all__ = [
    "UrdfComparison",
    "UrdfExport",
    "compare_urdf",
    "constant_origins",
    "export_tables",
    "export_urdf",
    "read_linuxcnc_comp",
    "read_tables_csv",
    "urdf_only_model",
    "write_linuxcnc_comp",
    "write_siemens_cec",
    "write_tables_csv",
]
