"""The learned 2D baseline: a CircleNet-style detector (CenterNet with circles; Yang et al., MICCAI 2020).

Modules (import them directly; this package imports nothing, so that ONNX inference never
pays for torch):
    imaging      the image contract shared by training and inference: image.png as RGB, padding
                 to multiples of 32, the stride-4 grid, numpy decoding (no torch)
    model        CircleNetConfig, CircleNet (ResNet-18-style + FPN neck, or stacked hourglass), decode
    loss         penalty-reduced focal loss + L1 offset / radius
    data         dataset folder reading, validation split, augmentation, target rendering
    train        train(train_dir, out_dir, config, seed), COCO circle mAP for validation
    onnx_export  export_onnx(model, path): opset 17, free batch, height and width, config in the metadata
    infer        CircleNetDetector(model.onnx): ONNX Runtime on the CPU; any image size, scaled to the
                 training focal length
"""
