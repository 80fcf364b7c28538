"""The JSON weight manifest of a Fish Sale Negotiator (FSN): every number addressed by meaning.

A manifest names each neuron and, inside it, each incoming weight by the name of its source:
``external_sensor.PG.weights.price`` is the weight from the input ``price`` into the
high-price neuron PG. Missing or unknown names, non-finite numbers and out-of-range settings are
refused by pydantic with the exact path of the offending value (``loc``).

Layers (paper, "The Server and Fish Sale Negotiator"; docs/auction.md):
* inputs (8): price p, length l, weight w, gill colour g, sub-type flags st1..st3, previous
  buy fraction f.
* ``external_sensor`` (ES, 4 neurons): PG (price too high), SZ (size), LSR (limited supply
  rush), ST (preferred sub-type); each a linear map of the inputs then its activation.
* ``decision`` (FC, 3 neurons): B buy, L hold (want a lower price), Q quit; linear in ES.
* ``pfc`` (prefrontal cortex): ``judgement`` PGL, BC, FQ read the softmax of
  [PG, SZ, LSR, ST, B, L, Q]; ``verdict`` T (true) and F (false) read tanh of the judgement.
* ``augmentation``: implicit contrastive augmentation (copies D_ic, noise σ, noiseless inputs).
* ``fine_tuning``: the participant's own SRD settings (epochs, batch size, learning rate).
"""

from __future__ import annotations

import json
import re
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, Final, Literal

from pydantic import (
    BaseModel,
    BeforeValidator,
    ConfigDict,
    Field,
    GetCoreSchemaHandler,
    GetJsonSchemaHandler,
    ValidationError,
    field_validator,
)
from pydantic.json_schema import JsonSchemaValue
from pydantic_core import PydanticCustomError, core_schema

SCHEMA_VERSION: Final = 1
INPUTS = ("price", "length", "weight", "gill", "st1", "st2", "st3", "buy_fraction")
ES_NEURONS = ("PG", "SZ", "LSR", "ST")
DECISIONS = ("B", "L", "Q")
PFC_SOURCES = ES_NEURONS + DECISIONS
JUDGEMENTS = ("PGL", "BC", "FQ")
VERDICTS = ("T", "F")


def _float_sized(value: Any) -> Any:
    """Refuse an integer no float can hold (``10**400``) as out of range, at its path: pydantic
    would call it "not a valid number", which a reader takes for a typo."""
    if isinstance(value, int) and not isinstance(value, bool):
        try:
            float(value)
        except OverflowError:
            raise PydanticCustomError(
                "finite_number",
                "out of range: not a finite float (an integer beyond ±1.8e308)",
            ) from None
    return value


InFloatRange = BeforeValidator(_float_sized)
"""A float field's metadata: an integer beyond the float range is refused as such."""
FiniteFloat = Annotated[float, Field(strict=True, allow_inf_nan=False), InFloatRange]
"""A finite JSON number (strict: ``"0.2"`` and ``true`` are not numbers)."""
Participant = Annotated[str, Field(min_length=1, max_length=64, pattern=r"^[A-Za-z0-9_.\-]+$")]
"""A participant's name as a lookup takes it (``GET /participants/{name}``, a list's filter):
letters, digits, ``_``, ``.``, ``-``."""
NewParticipant = Annotated[
    Participant,
    # said in the schema; a server refuses it by name (``name_problem``)
    Field(json_schema_extra={"not": {"pattern": r"^[-_.]+$"}}),
]
"""A participant's name as a manifest gives it: at least one letter or digit, too."""


def name_problem(participant: str) -> str | None:
    """Why a server takes no submission under ``participant`` though the manifest is valid, or
    None: a name of separators only has nothing to read (and '.' or '..' is a path segment,
    which no URL of the participant could name); names are compared with their separators
    made one and those at the ends left out, so '-', '--' and '_' would all read alike."""
    if participant.strip("-_."):
        return None
    return (
        "a participant's name needs a letter or a digit: a name of '-', '_' and '.' only has "
        "nothing to read ('.' and '..' are even path segments, which no URL could name)"
    )


_UNREADABLE = (
    "\x00-\x08\x0b\x0c\x0e-\x1f\x7f-\x9f"  # control characters but tab and line breaks
    "\u061c\u200e\u200f\u202a-\u202e\u2066-\u2069"  # bidirectional marks and overrides
    # invisible: soft hyphen, Hangul fillers, Mongolian vowel separator, zero-width space,
    # word joiner and invisible operators, zero-width no-break space, interlinear annotation
    "\xad\u115f\u1160\u180e\u200b\u2060-\u2064\u3164\uffa0\ufeff\ufff9-\ufffb"
    # invisible too: combining grapheme joiner, Khmer inherent vowels, Mongolian variation
    # selectors, an unassigned format and the deprecated ones, the variation selectors but the
    # emoji's two, Arabic and Syriac marks set before a number, the object replacement mark,
    "\u034f\u17b4\u17b5\u180b-\u180d\u180f\u2065\u206a-\u206f\ufe00-\ufe0d"
    "\u0600-\u0605\u06dd\u070f\u0890\u0891\u08e2\ufffc\ufff0-\ufff8"
    "\u2800"  # the braille blank: a cell with no dot, a name or note that shows nothing
)
_TAGS = "\U000e0000-\U000e0fff"
"""Tag characters (invisible letters: hidden text), variation selectors 17-256 and the rest of
that default-ignorable block, behind the UTF-16 lead surrogates U+DB40 to U+DB43, which the
JSON Schema's pattern refuses."""
_ASTRAL = "\U000110bd\U000110cd\U00013430-\U0001343f\U0001bca0-\U0001bca3\U0001d173-\U0001d17a"
"""Invisible formats beyond the Basic Multilingual Plane whose lead surrogate leads visible
characters too (Kaithi, shorthand, musical symbols): the server refuses them, the JSON
Schema's pattern cannot say them."""
_JOINER = "[\u200c\u200d\ufe0e\ufe0f]"
_THIRD_JOINER = f"(?<={_JOINER}{_JOINER}){_JOINER}"
"""Zero-width joiners and the emoji's variation selectors stay (scripts and emoji need them,
two in a row at most: U+FE0F then U+200D), but not in runs, which spell hidden text."""
_LINE_BREAKS = "\t\n\r\u2028\u2029"  # and U+0085, U+000B, U+000C: control characters


def _escaped(characters: str) -> str:
    """``characters`` (a regex class body of literal characters and ranges) with every one
    written as an escape, for the JSON Schema's ECMA-262 ``pattern``."""
    return "".join(f"\\u{ord(c):04x}" if c != "-" else "-" for c in characters)


@dataclass(frozen=True)
class _Readable:
    """A text check (pydantic metadata): the validator, and the same rule in the JSON Schema
    as a ``pattern`` (joined with a ``pattern`` the field has already, such as ``\\S``)."""

    refused: str
    """The characters refused, as a regex class body."""

    def check(self, text: str) -> str:
        found = re.search(f"[{self.refused}{_TAGS}{_ASTRAL}]|{_THIRD_JOINER}", text)
        if found is not None and found.group() in _LINE_BREAKS:
            raise PydanticCustomError(
                "not_one_line",
                "must be one line, without tabs: U+{code} at {at}",
                {"code": f"{ord(found.group()):04X}", "at": found.start()},
            )
        if found is not None:
            raise PydanticCustomError(
                "control_character",
                "must not contain control, invisible or bidirectional characters: U+{code} at {at}",
                {"code": f"{ord(found.group()):04X}", "at": found.start()},
            )
        return text

    def __get_pydantic_core_schema__(
        self, source: Any, handler: GetCoreSchemaHandler
    ) -> core_schema.CoreSchema:
        return core_schema.no_info_after_validator_function(self.check, handler(source))

    def __get_pydantic_json_schema__(
        self, schema: core_schema.CoreSchema, handler: GetJsonSchemaHandler
    ) -> JsonSchemaValue:
        json_schema = handler(schema)
        allowed = f"[^{_escaped(self.refused)}\\udb40-\\udb43]*"  # ECMA-262 reads UTF-16 units
        also = json_schema.get("pattern")
        runs = f"(?![\\s\\S]*[{_escaped(_JOINER[1:-1])}]{{3}})"  # _THIRD_JOINER, said so
        json_schema["pattern"] = (
            f"^{runs}(?=[\\s\\S]*(?:{also})){allowed}$" if also else f"^{runs}{allowed}$"
        )
        return json_schema


PlainText = _Readable(_UNREADABLE)
"""Text people read (a description, a note): no control characters but tab and line breaks,
no bidirectional overrides (stored text shows what it says, and every database stores it)."""
PlainLine = _Readable(_UNREADABLE + _LINE_BREAKS)
"""The same on one line (a name)."""


def _json_integer(value: Any) -> Any:
    """Refuse anything but a JSON integer (``1.0`` and ``true`` compare equal to 1)."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise ValueError("must be an integer")
    return value


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", allow_inf_nan=False, frozen=True)


class InputWeights(_Strict):
    """One weight per input channel, by name."""

    price: FiniteFloat
    length: FiniteFloat
    weight: FiniteFloat
    gill: FiniteFloat
    st1: FiniteFloat
    st2: FiniteFloat
    st3: FiniteFloat
    buy_fraction: FiniteFloat


class SensorWeights(_Strict):
    """One weight per external-sensor neuron, by name."""

    PG: FiniteFloat
    SZ: FiniteFloat
    LSR: FiniteFloat
    ST: FiniteFloat


class PfcSourceWeights(_Strict):
    """One weight per PFC source neuron (softmax of ES and FC activations), by name."""

    PG: FiniteFloat
    SZ: FiniteFloat
    LSR: FiniteFloat
    ST: FiniteFloat
    B: FiniteFloat
    L: FiniteFloat
    Q: FiniteFloat


class JudgementWeights(_Strict):
    """One weight per PFC judgement neuron, by name."""

    PGL: FiniteFloat
    BC: FiniteFloat
    FQ: FiniteFloat


class ThresholdActivation(_Strict):
    """T(x) = tanh(leaky_relu(a·(x − c), negative_slope))."""

    kind: Literal["threshold"]
    a: Annotated[float, Field(strict=True, gt=0, le=1000, allow_inf_nan=False), InFloatRange]
    c: Annotated[float, Field(strict=True, ge=-1000, le=1000, allow_inf_nan=False), InFloatRange]
    negative_slope: Annotated[
        float, Field(strict=True, ge=0, le=1, allow_inf_nan=False), InFloatRange
    ]


class BelowThresholdActivation(_Strict):
    """BT(x) = tanh(−leaky_relu(a·(x − c), negative_slope)) + 1."""

    kind: Literal["below_threshold"]
    a: Annotated[float, Field(strict=True, gt=0, le=1000, allow_inf_nan=False), InFloatRange]
    c: Annotated[float, Field(strict=True, ge=-1000, le=1000, allow_inf_nan=False), InFloatRange]
    negative_slope: Annotated[
        float, Field(strict=True, ge=0, le=1, allow_inf_nan=False), InFloatRange
    ]


class SelectiveActivation(_Strict):
    """S(x) = ε / (ε + x²)."""

    kind: Literal["selective"]
    epsilon: Annotated[float, Field(strict=True, gt=0, le=1, allow_inf_nan=False), InFloatRange]


Activation = Annotated[
    ThresholdActivation | BelowThresholdActivation | SelectiveActivation,
    Field(discriminator="kind"),
]


class SensorNeuron(_Strict):
    """An external-sensor neuron: weights from the 8 inputs, a bias, an activation."""

    weights: InputWeights
    bias: FiniteFloat
    activation: Activation


class ExternalSensor(_Strict):
    """ES: PG (price too high), SZ (big fish), LSR (limited supply rush), ST (sub-type)."""

    PG: SensorNeuron
    SZ: SensorNeuron
    LSR: SensorNeuron
    ST: SensorNeuron


class DecisionNeuron(_Strict):
    """An FC neuron: weights from the 4 ES neurons and a bias; no activation."""

    weights: SensorWeights
    bias: FiniteFloat


class Decision(_Strict):
    """FC: B (buy), L (hold, want a lower price), Q (quit); greedy argmax, ties → B."""

    B: DecisionNeuron
    L: DecisionNeuron
    Q: DecisionNeuron


class JudgementNeuron(_Strict):
    """A PFC judgement neuron: weights from softmax([PG, SZ, LSR, ST, B, L, Q])."""

    weights: PfcSourceWeights
    bias: FiniteFloat


class VerdictNeuron(_Strict):
    """A PFC verdict neuron: weights from tanh([PGL, BC, FQ])."""

    weights: JudgementWeights
    bias: FiniteFloat


class Judgement(_Strict):
    """PGL: holding at a high price is right; BC: buying cheap is right; FQ: false quitting."""

    PGL: JudgementNeuron
    BC: JudgementNeuron
    FQ: JudgementNeuron


class Verdict(_Strict):
    """T: the decision was right; F: it was wrong."""

    T: VerdictNeuron
    F: VerdictNeuron


class Pfc(_Strict):
    """Prefrontal cortex: the model's own judge of its decisions (self reward)."""

    judgement: Judgement
    verdict: Verdict
    trainable: Annotated[bool, Field(strict=True)] = True


InputName = Literal["price", "length", "weight", "gill", "st1", "st2", "st3", "buy_fraction"]


class Augmentation(_Strict):
    """Implicit contrastive augmentation: copy 0 clean, copies 1.. jittered by N(0, σ²)."""

    copies: Annotated[int, Field(strict=True, ge=1, le=16)] = 5
    noise_std: Annotated[
        float, Field(strict=True, ge=0, le=1, allow_inf_nan=False), InFloatRange
    ] = 0.01
    noiseless_inputs: tuple[InputName, ...] = Field(
        default=("st1", "st2", "st3"), max_length=len(INPUTS)
    )

    @field_validator("noiseless_inputs", mode="before")
    @classmethod
    def _few(cls, names: Any) -> Any:
        """At most one entry per input, counted before each entry is read (a list of a
        hundred thousand wrong entries is one problem, not a hundred thousand)."""
        if isinstance(names, list | tuple) and len(names) > len(INPUTS):
            raise PydanticCustomError(
                "too_long",
                "at most {most} inputs (one per input), not {given}",
                {"most": len(INPUTS), "given": len(names)},
            )
        return names

    @field_validator("noiseless_inputs")
    @classmethod
    def _canonical_order(cls, names: tuple[str, ...]) -> tuple[str, ...]:
        """A set of inputs: kept once each, in input order, so manifests compare equal."""
        return tuple(name for name in INPUTS if name in names)


class FineTuning(_Strict):
    """The participant's SRD fine-tuning settings (plain SGD over all parameters)."""

    epochs: Annotated[int, Field(strict=True, ge=0, le=10)] = 0
    batch_size: Annotated[int, Field(strict=True, ge=1, le=64)] = 16
    learning_rate: Annotated[
        float, Field(strict=True, ge=0, le=1, allow_inf_nan=False), InFloatRange
    ] = 0.0


class Manifest(_Strict):
    """A Fish Sale Negotiator, every number addressed by meaning (see module docstring)."""

    schema_version: Annotated[Literal[1], BeforeValidator(_json_integer)] = SCHEMA_VERSION
    kind: Literal["fish-sale-negotiator"] = "fish-sale-negotiator"
    participant: NewParticipant
    description: Annotated[str, Field(max_length=2000), PlainText] = ""
    augmentation: Augmentation = Augmentation()
    external_sensor: ExternalSensor
    decision: Decision
    pfc: Pfc
    fine_tuning: FineTuning = FineTuning()


class ManifestError(ValueError):
    """A manifest was refused; ``errors`` lists ``{"path": "a.b.c", "message": ...}``, with the
    schema's error ``type`` (``float_type``, ``missing``, ...) where the schema refused it."""

    def __init__(self, errors: list[dict[str, str]]) -> None:
        self.errors = errors
        super().__init__("; ".join(f"{e['path']}: {e['message']}" for e in errors))


_ACTIVATION_TAGS = frozenset(("threshold", "below_threshold", "selective"))


def without_tags(loc: Sequence[int | str]) -> list[int | str]:
    """A pydantic error location as a path into the JSON, without pydantic's union tags
    (``external_sensor.PG.activation.threshold.a`` → ``external_sensor.PG.activation.a``)."""
    return [
        part
        for i, part in enumerate(loc)
        if not (part in _ACTIVATION_TAGS and i > 0 and loc[i - 1] == "activation")
    ]


def _json_path(loc: tuple[int | str, ...]) -> str:
    """The dotted JSON path of a pydantic error location (``without_tags``)."""
    return ".".join(str(part) for part in without_tags(loc)) or "$"


def _refused(exc: ValidationError) -> ManifestError:
    return ManifestError(
        [
            {"path": _json_path(tuple(err["loc"])), "message": err["msg"], "type": err["type"]}
            for err in exc.errors()
        ]
    )


def parse_manifest(data: Any) -> Manifest:
    """Validate a decoded JSON object into a Manifest, or raise ManifestError naming each path."""
    try:
        return Manifest.model_validate(data)
    except ValidationError as exc:
        raise _refused(exc) from exc


def parse_manifest_json(text: str | bytes) -> Manifest:
    """Validate JSON text (NaN and Infinity tokens are read, then refused by path)."""
    try:
        return Manifest.model_validate_json(text)
    except ValidationError as exc:
        raise _refused(exc) from exc


def manifest_json_schema() -> dict[str, Any]:
    """The published JSON Schema of the manifest."""
    return Manifest.model_json_schema()


SCHEMA_FILE = Path(__file__).with_name("fsn_manifest.schema.json")
"""Where the published schema lives (regenerate with ``python -m agents.manifest``)."""


def manifest_json_schema_text() -> str:
    """The schema as the exact text of ``SCHEMA_FILE``."""
    schema = {
        "$schema": "https://json-schema.org/draft/2020-12/schema",
        **manifest_json_schema(),
    }
    return json.dumps(schema, indent=2, ensure_ascii=False) + "\n"


if __name__ == "__main__":
    SCHEMA_FILE.write_text(manifest_json_schema_text())
    print(f"wrote {SCHEMA_FILE}")
