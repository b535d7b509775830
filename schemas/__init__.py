"""The magmesh wire contract: key builders (:mod:`schemas.keys`) and message types (:mod:`schemas.messages`)."""

from . import keys, messages
from .messages import MESSAGES, SchemaError, decode, encode, make, validate

__all__ = ["keys", "messages", "MESSAGES", "SchemaError", "decode", "encode", "make", "validate"]
