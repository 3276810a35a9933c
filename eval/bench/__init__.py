"""The benchmark: the methods, the runs, their scores and reports, above the metrics, the detector
and the baselines. Import the modules by name (this package imports nothing):

    registry      each method's configuration and adapter (``build_methods``)
    tasks         the one task loop: methods over a dataset's scenes, seeded (``run_methods``)
    cache         prediction sets on disk and their resume keys
    seeds         the detection seed of each scene
    studies       Table 2 on `paper` and the oracle's ceiling, cached
    oracle        the detector's own verification started from the true centre
    evaluate      ``evaluate``: run, score and report datasets (`spherebench evaluate`)
    benchmark     ``run_benchmark``: the whole of `make eval` (`spherebench eval`)
    report        scoring prediction sets; metrics.json, README.md, provenance.json
    tables        Markdown and CSV tables
    figures       the benchmark's figures
    recorded      what a recorded dataset's ground truth is; Table 3 beside another evaluation
    transfer      each analytic preset beside its stereo twin
    speed         the 3D detector's accuracy and speed per configuration (`spherebench bench`)
    sweep         the 3D detector over several seeds (`spherebench sweep`)
    robustness    the improved detector across sensor conditions (`spherebench robustness`)
    stereo_calibration  the stereo sensor model against Intel's figures
    paper_numbers the paper's published figures
"""
