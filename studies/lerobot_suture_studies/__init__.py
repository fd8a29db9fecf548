"""The studies behind lerobot-suture's choices, apart from the product they study.

- :mod:`.score_study`: the gate's uncertainty scores compared on validation seeds (``lerobot-suture score-study``);
- :mod:`.benchmark_ood`: the gate against the failure-detection field's detectors on the same rollouts
  (``lerobot-suture benchmark-ood``), with its scoring (:mod:`.benchmark_ood_scoring`) and tables and figures
  (:mod:`.benchmark_ood_report`);
- :mod:`.robustness`: policies side by side under the shifts, with the gate (``lerobot-suture robustness-report``).

This package imports :mod:`lerobot_suture`; nothing in the product imports it (``tests/test_layout.py``). The
product's CLI runs its commands by name, when installed (``pip install -e ./studies``, which ``make install``
does).
"""
