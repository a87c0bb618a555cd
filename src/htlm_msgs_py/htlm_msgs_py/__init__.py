"""The HTLM wire contract: topic names, QoS profiles, record schemas on std_msgs/String, signing; and the one
converter of plain data (files, parameters) to settings dataclasses (`validation.convert`).

Importing this package (and its modules topics, qos, schema, signing, validation) needs no rclpy; only
`htlm_msgs_py.ros` touches ROS.
"""

from .schema import SCHEMAS, Schema, WireError, decode, encode, limits
from .signing import Signer, SigningError, signer_from_env
from .validation import ConversionError, convert

WIRE_VERSION = 1
"""Version of the wire contract as a whole; every record also carries its own schema version."""

__all__ = [
    "SCHEMAS",
    "WIRE_VERSION",
    "ConversionError",
    "Schema",
    "Signer",
    "SigningError",
    "WireError",
    "convert",
    "decode",
    "encode",
    "limits",
    "signer_from_env",
]
