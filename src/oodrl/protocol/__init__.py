"""The benchmark protocol (SPEC §1-§3, §9, §15, §19): which streams each set holds and from which
seeds (`streams`), recorded data as a clean set (`recorded`), what a fault costs the agent and
its tiers (`impact`, `tiers`), and how a fitted detector's scores of a set are computed
(`scoring`). The stages (`oodrl.stages`) call it; it writes nothing itself."""
