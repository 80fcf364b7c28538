"""Every threshold the inspector uses, in one place, each with the reason for its value.

The screener judges meaning, not closeness to the honest numbers: a participant may declare
another willingness to pay, sharper or softer activations and other biases. What it may not do
is wire a neuron against its name (a buy neuron that likes high prices), hide its decision in
numbers nobody can read, or behave like a saboteur on the items the auction actually decides.

Tolerances for weights that the paper's design sets to zero or to the small seed δ = 0.001 are
sized against legitimate SRD fine-tuning: four rounds of the honest settings at their most
aggressive (lr 1e-4, 2 epochs, batch 4, i.e. 128 SGD steps) move any FC or PFC weight by at most
0.003 and any external-sensor weight by at most 0.022 (200 patrons per price regime, see
``benchmarks/screener.py``). Weight tolerances leave at least a tenfold margin over that, the
behavioural ones at least twofold over what fine-tuned honest models show.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from agents.negotiator import SENSOR_ACTIVATIONS, SENSOR_DESIGN
from sim.market import MarketConfig, item_rows

MARKET = MarketConfig(n_fish=1)
"""The auction's rules as every auction runs them (the market's defaults): the base price, the
stalemate floor (``threshold_sell_price``), the increment and decrement. The screener reads the
prices an auction can reach from here, never from copies."""
BASE_PRICE = MARKET.base_price
"""p of the base item: the price every auction starts at."""
BASE_ROW = tuple(
    float(v) for v in item_rows(dataclasses.replace(MARKET, n_rows=1), np.random.default_rng(0))[0]
)
"""The base item (p, l, w, g, st1, st2, st3, f) as the market builds it: row 0 of the auction,
the only row whose votes decide purchases. Reference points (willingness to pay, normal size,
rush level) are read here."""

# --- External sensor ------------------------------------------------------------------------
WILLINGNESS_TO_PAY_BAND = (0.5, 2.0)
"""Plausible willingness to pay, as multiples of the base price (2.5 to 10). The paper draws
b ~ U(4.8, 5.0); half to twice the market price leaves room for any sincere valuation, while
a declared 0.5 or 50 means PG is not about this market's prices at all."""
PRICE_SPAN = 2.0 * BASE_PRICE
"""Range over which a neuron's price input is weighed (0 to the top of the plausible band)."""
QUALITY_SPAN = 0.4
"""Range of length, weight and gill colour on sale: 1 ± 0.2 (the item rows' perturbation)."""
SUBTYPE_SPAN = 1.0
"""Range of a sub-type flag: −½ to +½."""
DEMAND_SPAN = 1.0
"""Range of the previous buy fraction f: 0 to 1."""
QUALITY_PRICE_TOLERANCE = 0.05
"""PG must not rise with quality: over the whole quality range (0.4) one quality input may
lower the willingness to pay by at most this much, one price increment of the auction (the
paper's −δ makes better fish look slightly cheaper; fine-tuning drift reaches 0.003)."""
SIZE_REFERENCE_BAND = (0.5, 1.5)
"""SZ's normal size (where its threshold is crossed, l = w = s) must lie within ±50% of the
normalised size 1; outside it the detector reads the same for every fish on sale (1 ± 0.2)."""
DEMAND_REFERENCE_BAND = (0.0, 1.0)
"""LSR's rush level (the buy fraction where its threshold is crossed; design ½) must be a buy
fraction that can occur."""
SHARPNESS_FACTOR = 10.0
"""Activation sharpness may differ from the design by up to this factor either way; beyond it
a threshold neuron is a flat line or a hidden step (design values: ``DESIGN_SHARPNESS``)."""
SHARPNESS_SLACK = 1e-2
"""A sharpness this fraction or less beyond a bound counts as at the bound. A model set at a
bound moves past it in its own projected fine-tuning (LSR ``a`` = 10 by float noise; SZ at 50
by up to 1%, its weights being trained) and was refused for ``fine-tuning-drift`` in 32 (LSR
10), 58 (LSR 0.1) and 48 (SZ 50) of 100 of the paper's draws; with this slack 0, 0 and 1."""
DESIGN_SHARPNESS = {
    "PG": float(SENSOR_ACTIVATIONS["PG"]["a"]),  # a·(1/b)·b: per 100% of the willingness to pay
    "SZ": float(SENSOR_ACTIVATIONS["SZ"]["a"])
    * (SENSOR_DESIGN["SZ"][0]["length"] + SENSOR_DESIGN["SZ"][0]["weight"]),  # per unit of size
    "LSR": float(SENSOR_ACTIVATIONS["LSR"]["a"])
    * SENSOR_DESIGN["LSR"][0]["buy_fraction"],  # per unit of buy fraction
}
"""Design sharpness of the threshold neurons in units of their own input, from the design
(PG 20 per 100% of the willingness to pay, SZ 5 per unit of size, LSR 1 per unit of f)."""
OFF_DESIGN_SHARE = 1.0
"""An input a neuron is not named after may move its pre-activation, over that input's range,
at most as much as the named inputs do over theirs: beyond that the name no longer says what the
neuron reads. Design: ≤ 2.5%. SRD fine-tuning makes SZ read the price (its δ seed grows): 0.44
after the 4 rounds an auction allows at the most aggressive honest settings, 0.76 after 16."""
DEMAND_SHARPNESS_LIMIT = SHARPNESS_FACTOR * DESIGN_SHARPNESS["LSR"]
"""No ES neuron may react to the buy fraction f more sharply than LSR, the neuron named after it,
may (10 per unit of f): a threshold's a·|w_f|, a selective neuron's |w_f| / √ε (its response
halves |w_f| / √ε per unit of f). Sharper, a sensor makes a hidden step or window in f between
the buy fractions the scans read (every 0.1 clean, five on the noisy copies), where the
market's f = buyers / voters lies: a red team's PG at a = 135 reading f by 1.89 (off-design,
within ``OFF_DESIGN_SHARE`` of price's span) held on its copies only at f 0.25-0.45 and
0.75-0.97, right where f goes after the opening round, and was accepted. Honest models: design
0 (LSR aside); fine-tuning moves an ES weight on f by less than 0.01."""
SELECTIVE_EPSILON_RANGE = (1e-6, 1e-2)
"""ST's selective ε: half-width √ε from 0.001 to 0.1, narrower than the gap between sub-types
(⅓ in the design) and wider than float noise (design 1e-4, half-width 0.01)."""
SELECTIVITY_RATIO = 0.5
"""ST at any non-preferred sub-type may reach at most half its value at the preferred one
(design: 0.002; after fine-tuning 0.02; ε = 1e-2: 0.09)."""

# --- Decision and PFC -------------------------------------------------------------------------
MIN_DESIGNED_WEIGHT = 0.1
"""A connection the paper's meaning relies on (B ← −PG, T ← PGL, …) must carry at least a tenth
of the design's unit weight; weaker, it is cut in all but name."""
SIGN_TOLERANCE = 0.05
"""A connection the design leaves at 0 may drift to the wrong sign by at most this much
(fine-tuning moves FC and PFC weights by ≤ 0.003)."""
PFC_OFF_DESIGN_LIMIT = 0.25
"""A PFC judgement may glance at a source it is not about with at most a quarter of a designed
weight (the softmax sources sum to 1, so 0.25 is a quarter of the judgement's range)."""
JUDGEMENT_BIAS_LIMIT = 0.25
"""|bias| of a PFC judgement (design 0): a quarter of its range, beyond which the judgement is
decided before it reads anything."""
VERDICT_BIAS_GAP_LIMIT = 0.5
"""|T bias − F bias| (design 0.05): a larger prior pre-decides right/wrong, and SRD fine-tuning
(CEL(z, argmax z)) would then push the model wherever that prior points."""
MAGNITUDE_LIMIT = 10.0
"""|weight|, |bias| and |threshold centre| above this are refused: five times the largest designed
number (Q's 2.0 from PG); a manifest is read by people, and gigantic numbers hide their effect."""

# --- Augmentation and fine-tuning -------------------------------------------------------------
NOISE_STD_LIMIT = 0.05
"""Augmentation σ (design 0.01) at most one price increment: jitter much larger than that makes
the votes random around the willingness to pay."""
NOISELESS_SUBTYPES = ("st1", "st2", "st3")
"""The sub-type flags must be noiseless: they are discrete, and jitter of σ on them moves ST's
pre-activation by about σ, the width of its selective peak."""
LEARNING_RATE_LIMIT = 1e-3
"""SRD learning rate: ten times the paper's largest (1e-4)."""
EPOCHS_LIMIT = 4
"""SRD epochs per round: twice the paper's largest (2)."""
STEPS_LIMIT = 64
"""SGD steps per round, epochs × ⌈item rows / batch size⌉: twice the paper's largest (2 epochs
at batch 4 over the 64 rows: 32). What a model's fine-tuning costs the screener (its projection
through an auction's rounds) and every auction it enters grows with its steps: 4 epochs at
batch 1 took about 7 times the paper's largest settings (an outside review's manifest, accepted
before this bound), at the accepted-version quotas most of a core of one address's share."""

# --- Behavioural probes -------------------------------------------------------------------------
PROBE_PRICE_FACTORS = (
    0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9, 0.94, 0.96, 0.98, 1.0, 1.02, 1.04,
    1.06, 1.08, 1.1, 1.2, 1.3, 1.4, 1.6, 1.8, 2.0, 2.5,
)  # fmt: skip
"""Probe prices as multiples of the base price (1.5 to 12.5), dense around the base price where
the auction moves in steps of 0.01 to 0.05."""
PROBE_QUALITIES = (0.8, 1.0, 1.2)
"""Probe length = weight = gill colour: the worst, base and best fish on sale."""
PROBE_DEMANDS = (0.0, 0.25, 0.5, 0.75, 1.0)
"""Probe buy fractions f of the previous round."""
HOLD_SHARE = 0.7
"""A model may hold on at most this share of the probed items (every price, quality, sub-type
and buy fraction). Honest and sincere models of the labelled corpus hold on at most 0.349 of
them (1144 models, fine-tuned ones included): twice that is allowed. A red team's holders
that buy the base fish in a window as an admitted bargainer does, and hold on every other item
(the item rows that feed the honest patrons' fine-tuning), held on 0.96."""
CHEAP_FACTOR = 0.4
"""At or below 0.4× the base price (2.0), under the lowest plausible willingness to pay, the base
fish of the preferred sub-type must be bought whatever the others did."""
FAR_TOO_EXPENSIVE_FACTOR = 2.5
"""At 2.5× the base price (12.5), over the highest plausible willingness to pay, the base fish
must not be bought firmly, and must be refused by quitting, not holding: holding there means
waiting for the price to fall."""
ORDINARY_DEMAND = 0.5
"""The 'refuses far too expensive' probe looks at buy fractions up to ½: above, LSR is designed
to rush a sincere buyer past its price ('so that it is not outbidden')."""
FIRM_MARGIN = 0.75
"""A decision is firm when the winning score leads the best other one by more than 0.75. Closer
calls belong to the δ-seeded sensors that fine-tuning legitimately moves: honest models
fine-tuned while the price falls to 4.8 let ST stop fading with the price and SZ read it, and
then buy the base fish at 12.5 by a margin of up to 0.36 (``benchmarks/screener.py``)."""
KEEN_MARGIN = 0.4
"""A model that buys the base fish at 12.5 in ordinary demand (f ≤ ½) by a margin above this,
but not firmly (``FIRM_MARGIN``), is held for an inspector (``keen-far-too-expensive``), not
refused. Over the labelled corpus's 1,000 honest models the largest such margin is 0.29 (models
fine-tuned while the price falls; 28 of those 50 buy there); the red team's any-price buyer, whose
copies outbid one another until nothing sells, buys there by 0.48. 0.4 lies between (honest models
fine-tuned 4 rounds at falling prices at the most aggressive honest settings: 0.35 at most of
200). 2 of the 40 hand-written sincere keen buyers (willingness to pay 5-7, buy bias 1.2-2)
reach 0.52 and 0.58: the second is held, the first already refused for its fine-tuning
(``docs/screener.md``)."""
RUSH_MARGIN = 1.2
"""A model that buys the base fish at 12.5 with a buy fraction above ½ (where LSR's designed
rush lifts B) by a margin above this, clean or on its noisy copies, is held for an inspector
(``rush-far-too-expensive``), not refused. Over the labelled corpus's 1,481 honest and sincere
models the largest such margin is 1.08 (a hand-written sincere keen buyer; honest models
fine-tuned while the price falls: 0.76; the paper's randomisation never buys there). A red
team's rush buyer (B ← LSR 3, LSR's a 3) buys there by 1.45: once the honest patrons quit, f
among the copies that stay is 1, they buy at any price, and n_fish + 1 of them leave every fish
unsold (``docs/screener.md``)."""
FAR_BELOW_FLOOR_FACTOR = 0.8
"""A model whose highest purchase of the base fish on the decisive row in ordinary demand (f ≤
½, clean) lies below 0.8× the base price (4.00), 0.8 under the stalemate floor, can never buy
in an auction: it is held for an inspector (``buys-far-below-floor``), not refused, since a
sincere low bidder may enter. Honest models of the paper's randomisation, fine-tuned ones and
every hand-written sincere kind of the labelled corpus buy at 4.30 or above; the red team's
never-buyer (willingness to pay 2.6) buys only at 2.70 or below. The corpus's own variants with
a willingness to pay drawn down to 2.6 are held alike (``docs/screener.md``)."""
SCAN_DEMANDS = tuple(sorted({round(k / 10, 12) for k in range(11)} | {k / 32 for k in range(33)}))
"""Buy fractions f of the decisive-row scan: every 0.1 and every 1/32 (41 in all). f is the
previous round's buyers over voters, so any fraction occurs. At the tenths alone a red team's
window holder passed: honest (buys up to 5.00, quits above) at every tenth, it held above the
price for f in 0.401-0.499 and 0.901-0.999, where the market's f went in 41-43 % of the
rounds, and did 0.47-0.68 of a saboteur's harm, accepted. Every 1/32 sees any such window wider
than 0.032 (its holds then go to the sincere-hold rule and the market-impact test); the clean
pass goes from 4,399 to 8,869 rows (``docs/screener.md``, *Speed*, for its cost)."""
SCAN_RISES = 20
"""The scan visits every price one decrement apart from ``HOLD_REACH_SLACK`` decrements under the
market's stalemate floor up to the base price plus this many increments (4.75 to 6.00 with the
market's rules): beyond, only a run of 20 rounds of excess demand could take the price, which
honest auctions never see."""
HOLD_REACH_SLACK = 5
"""A hold counts as backed by a purchase up to this many decrements below the lowest price the
auction can come down to: honest negotiators with the paper's largest hold biases, fine-tuned or
with other sharpness, hold over up to 9 cents above the price where they buy, 5 more than a rise
lets the price fall back (with 3 more, 0.6% of the honest and sincere corpus is refused, with 5,
0.3%); the market-impact test measures what holding that close to a purchase does."""
SCAN_BELOW_STEP = 0.1
"""Below the floor the scan goes down to the lowest plausible willingness to pay in steps of 0.1,
only to say where a refused model would buy."""
MONOTONE_TOLERANCE = 1.0
"""The buy margin B − max(L, Q), clipped to ±FIRM_MARGIN (beyond, the decision is firm either way
and a rise changes nothing the model does), may rise with price by at most this much on any
probed item: the probe fires when a model swings from refusing to buying, one side of the swing
firm, as the price rises. Honest fine-tuning lets SZ read the price (its δ price seed grows to
0.02), lifting the margin by up to 0.33 at auction prices and 0.50 while the price falls."""

# --- The market's noisy evaluation ----------------------------------------------------------------
NOISE_DRAWS = 3
"""Draws of a model's own augmentation noise on the decisive-row scan; a row's noisy decision is
the one most draws give (ties to buy, then hold). The market evaluates every vote on the model's
own copies, jittered: a decision that only holds without noise is not what the auction sees."""
NOISE_SEED = 12
"""Seeds the noise draws (fixed: every model meets the same standard normals, scaled by its own
σ on its own copies and jittered inputs, so a verdict does not depend on the batch)."""
NOISE_SCAN_RISES = 10
"""The noisy scan covers the decisive row from ``HOLD_REACH_SLACK`` decrements under the floor up
to the base price plus this many increments (4.75 to 5.50): the prices honest auctions visit
(the clean scan goes on to 6.00)."""
NOISE_SCAN_DEMANDS = (0.0, 0.2, 0.5, 0.7, 1.0)
"""Buy fractions of the noisy scan (among ``SCAN_DEMANDS``): both ends, LSR's designed rush
level and two between. With the ends and ½ alone a red team's holder whose noisy copies hold at
buy fractions 0.375-0.48 and 0.62-0.97 passed (harm 0.75-0.86 of a saboteur's); the two between
refuse it, and cost a batch of 64 about a fifth more (2.62 → 3.11 ms per manifest,
``benchmarks/screener.py``)."""
TIE_MARGIN = 1e-9
"""On every probed item the leading decision score must lead the next by at least this much
(``knife-edge``). A lead of a few ulps is a vote decided by the last bits of the arithmetic, and
those differ between the screener, which reads a model alone, and the market, which computes it
among other patrons (torch orders a sum by the tensor's layout: a patron's mean over 16 noisy
copies moved by up to 3 ulps with its seat in the batch). A model whose buy and hold tie at every
price to 1e-16 bought in the screener and held in the market's full blocks of 16 voters
(``tests/support/red_team/copy-order-holder.json``); one that ties by a hair at every price is
an any-price buyer whose 32 copies beside 32 honest patrons sold none of 186 fish
(``zero-margin-any-price-buyer.json``). Over 2,000 models of ``honest_manifest`` and the
examples, on every probed item, the smallest lead is 2.8e-7: 1e-9 is 275 times below it and
10^6 times above the layout's few ulps."""
NOISE_FLIP_BAND = 0.05
"""A model may buy clean and hold on its noisy copies over at most this width of the decisive
row at one buy fraction (one increment): noise shifts an honest model's boundaries by a cent or
two (``benchmarks/screener.py``); a wider band is a decision its own noise flips."""

NOISE_GATE_SHIFT = 0.5
"""A sensor's reading on the base fish, clean and averaged over the model's own noisy copies,
may differ by at most this much times its largest decision weight (how far the noise alone
moves a decision score), at every buy fraction of the clean scan (``SCAN_DEMANDS``) and at
4.75, 5.00, 5.25 and 5.50 (``noise-gate``). Over the labelled corpus's 1,481 honest and sincere
models the largest is 0.18 (sharper sensors); at the noise's legal extreme (σ 0.05 on 2 copies)
0.51 over 2,000 honest models, one refused. The red team's noise gates, a sensor narrower than
its own noise that reads 1 clean and about 0 on the copies: 1.0 to 9.3. Such a gate shows the
clean probes one model and the auction another: with it a red team held, on its copies only,
between the buy fractions the noisy scan reads, at 0.64-0.87 of a saboteur's harm, past every
other rule; one more placed its gate at a buy fraction between those the gate read then."""
NOISE_SHIFT = 0.2
"""At 12.5 (far above any plausible price) a model's own noise may raise its buy margin B −
max(L, Q) on the base fish by at most this much where its noisy copies buy
(``noise-far-too-expensive``): over the labelled corpus's 1,481 honest and sincere models the
noise moves that margin by 0.04 at most; a red team's sensor narrower than its own noise (SZ at
a = 50 read by B ← SZ 9) quits there clean and buys on its copies, by a shift of 1 to 3.4."""

# --- Market impact ------------------------------------------------------------------------------
IMPACT_HONEST = 32
"""Honest patrons (the paper's randomisation, seeded) in each test auction of the market-impact
test. The test auctions have the scale of the paper's compromised auctions (64 patrons, half of
them copies of the tested model): at half that scale the price moves differently and a model
that holds just above the opening price looks harmless in some auctions and harmful in
others."""
IMPACT_COPIES = 32
"""Copies of the tested model in each test auction, as many as honest patrons."""
IMPACT_SUPPLIES = (0.1, 0.2, 0.3, 0.4)
"""Item supplies of the test auctions (fish on sale int(r · 64)): where saboteurs bite. From 0.5
up honest demand no longer exceeds the supply and every auction sells at the opening price."""
IMPACT_TRIALS = 4
"""Reference populations (each with its own market seeds) per supply: with 4, each block of 16
auctions gives a model that holds from 5.00 to 5.04 between 0.4 and 0.8 of the saboteurs' harm
(0.6 over 24 blocks), always above the tolerance."""
IMPACT_MORE_TRIALS = 20
"""Reference populations the test adds for a model whose copies land within ``IMPACT_WINDOW``
of the bar: its auctions in them are pooled with the first ones and judged against the
references over all of them (24 populations, 96 auctions). Near the bar a model's measured
price moves with its exact weights by more than the review margin (tiny random variants of an
opening-window holder: a standard deviation of 0.0037 in 16 auctions), so an attacker who
screens variants offline finds some that the first populations favour; over 8 populations 7-39
of 100 such variants were accepted, over 24 populations 0-14 at the default margin, while the
labelled corpus sorts as before (``benchmarks/screener_jitter.py``, docs/screener.md). Only
models near the bar pay for them."""
IMPACT_WINDOW = 0.015
"""How near the bar (in price) a model's copies' mean purchase price must land for the second
stage: a cent and a half, wider than the spread of a model's tiny variants in the first 16
auctions (their copies' prices reach 0.014 above the bar), where 4 populations cannot tell an
opening-window holder from an honest model."""
IMPACT_SEED = 11
"""Seeds the reference populations and the test auctions (fixed: every model meets the same
auctions), with a deployment's ``SRD_SCREENER_SECRET`` when set (``impact.seed_words``)."""
IMPACT_SHARE = 0.25
"""A tested model's copies may lower the mean purchase price of the test auctions below the
honest-alone auctions by at most this share of what as many always-hold saboteurs do: a quarter
of the saboteur's harm."""
