"""Lab bring-up: the scripted channel checkout (``pfma checkout``), and the attach/reattach
and view helpers of ``pfma monitor`` and ``pfma watch``. See docs/checkout.md."""

from tools.checkout.config import GROUPS, CheckoutConfig, load_checkout_config
from tools.checkout.panel import PanelState, parse_panel_off
from tools.checkout.report import FAIL, PASS, SKIP, Report, Result
from tools.checkout.runner import Checkout
from tools.checkout.target import FakeStimulus, LiveTarget, ServiceLost, SimTarget, make_sim_target

__all__ = ["GROUPS", "CheckoutConfig", "load_checkout_config", "Report", "Result", "PASS", "FAIL",
           "SKIP", "Checkout", "FakeStimulus", "LiveTarget", "PanelState", "ServiceLost", "SimTarget",
           "make_sim_target", "parse_panel_off"]
