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
    RunUrdfExport,
    UrdfComparison,
    UrdfExport,
    c0_model,
    compare_urdf,
    constant_origins,
    constant_projection,
    export_run_urdf,
    export_urdf,
    projection_commands,
    projection_misfit,
    urdf_only_model,
)

__all__ = [
    "RunUrdfExport",
    "UrdfComparison",
    "UrdfExport",
    "c0_model",
    "compare_urdf",
    "constant_origins",
    "constant_projection",
    "export_run_urdf",
    "export_tables",
    "export_urdf",
    "projection_commands",
    "projection_misfit",
    "read_linuxcnc_comp",
    "read_tables_csv",
    "urdf_only_model",
    "write_linuxcnc_comp",
    "write_siemens_cec",
    "write_tables_csv",
]
