"""The package://capsule_drake/ models (models/: capsule, EPM stage and arm, table)."""

from pathlib import Path

from pydrake.multibody.parsing import Parser

MODELS_DIR = Path(__file__).resolve().parents[1] / "models"
PACKAGE = "capsule_drake"


def configure_parser(parser: Parser) -> Parser:
    """Registers the package://capsule_drake/ models with a parser; returns it."""
    parser.package_map().AddPackageXml(str(MODELS_DIR / "package.xml"))
    return parser


def model_url(file_name: str) -> str:
    """The package URL of a file in models/, e.g. model_url("capsule.sdf")."""
    return f"package://{PACKAGE}/{file_name}"
