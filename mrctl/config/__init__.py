"""Configuration: the experiment schema and parameter sets, on the schema engine.

The engine (strict YAML, field types, key-path errors, reference tables) is
:mod:`mrctl.util.schema`; this package holds what mrctl's files may say.
"""

from mrctl.config.experiment import (
    CONFIG_VERSION,
    experiment_schema,
    load_experiment,
    schema_markdown,
    validate_experiment,
)
from mrctl.config.params import load_params_file, params_check
from mrctl.util.schema import (
    Bool,
    ConfigError,
    Custom,
    Node,
    Num,
    Section,
    Str,
    Union,
    load_yaml,
    validate_fields,
)

__all__ = [
    "CONFIG_VERSION", "Bool", "ConfigError", "Custom", "Node", "Num", "Section", "Str", "Union",
    "experiment_schema", "load_experiment", "load_params_file", "load_yaml", "params_check",
    "schema_markdown", "validate_experiment", "validate_fields",
]
