# Editable reflections pipeline. Only includes, `rule all` and where the report is; see workflow/rules/.
#   snakemake --cores 2 --config scene=demo            one scene end to end
#   snakemake --cores 2 --config scene=demo preset=ci  tiny sizes (CI)
#   snakemake --cores 2 --config batch=synthetic       three synthetic scenes + batch report
#   snakemake --cores 2 edits --config scene=demo      the scene's named edits (+ ground truth metrics)
#   snakemake --cores 2 benchmark_tracer               tracer benchmark table + JSON
#   snakemake --cores 2 sweep_all --config scene=demo  speed/accuracy sweep (Pareto plot, presets)
#   snakemake --cores 2 buffernet                      train + evaluate the small buffer network

report: "workflow/report/workflow.rst"


include: "workflow/rules/common.smk"
include: "workflow/rules/synth.smk"
include: "workflow/rules/poses.smk"
include: "workflow/rules/buffers.smk"
include: "workflow/rules/init.smk"
include: "workflow/rules/reconstruct.smk"
include: "workflow/rules/edit.smk"
include: "workflow/rules/benchmark.smk"
include: "workflow/rules/report.smk"


rule all:
    input:
        scene_targets(SCENES),
    default_target: True


onsuccess:
    print_reports()
