"""The benchmark: the methods, the runs, their scores and reports, above the metrics, the detector
and the baselines. Import the modules by name (this package imports nothing):

    registry      the methods, registered (``register_method``): configuration and adapter each
    tasks         the one task loop: methods over a dataset's scenes, seeded (``run_methods``)
    cache         prediction sets on disk and their resume keys
    seeds         the detection seed of each scene
    studies       Table 2 on `paper` and the oracle's ceiling, cached
    oracle        the detector's own verification started from the true centre
    evaluate      ``evaluate``: run, score and report datasets (`spherebench evaluate`)
    benchmark     ``run_benchmark``: the whole of `make eval` (`spherebench eval`)
    scoring       scoring prediction sets: COCO, 3D, sensor-grid and timing figures
    result_tables the results' tables from the scored sets
    prose         the README's reading of the results, by the registries' roles
    report        writing the results: metrics.json, tables/, figures/, README.md, provenance.json
    tables        Markdown and CSV tables
    figures       the benchmark's figures
    recorded      what a recorded dataset's ground truth is; Table 3 beside another evaluation
    transfer      each analytic preset beside its stereo twin
    calibration   the 3D methods' scores against their correctness: reliability bins, ECE
    speed         the 3D detector's accuracy and speed per configuration (`spherebench bench`)
    sweep         the 3D detector over several seeds (`spherebench sweep`)
    robustness    the improved detector across sensor conditions (`spherebench robustness`)
    stereo_calibration  the stereo sensor model against Intel's figures
    paper_numbers the paper's published figures
"""
