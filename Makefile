# sss2bathy — every command a user needs. `make` (or `make help`) lists them, grouped under
# the `##@` headings below (a target's help is its `## ...` comment).
# ARGS is passed through to Hydra, e.g.  make siren-cnn-n2d ARGS="trainer.max_epochs=50 seed=2"

SHELL := /bin/bash
.DEFAULT_GOAL := help
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
TORCH_SPEC ?= torch==2.13.0
ARGS ?=
SCALE ?= demo
export SSS2BATHY_ROOT := $(CURDIR)

.PHONY: help install test test-slow lint format demo prepare map report results paper \
	sweep-example sweep-siren bench schedule-study tb clean

##@ Install and check

help: ## Show this help (target names in colour only on a terminal)
	@if [ -t 1 ]; then on=$$'\033[36m'; off=$$'\033[0m'; else on=; off=; fi; \
	grep -hE '^([a-zA-Z0-9_-]+:.*?## |##@ )' $(MAKEFILE_LIST) | \
		awk -v on="$$on" -v off="$$off" 'BEGIN {FS = ":.*?## "} \
			/^##@ / {printf "%s%s\n", (n++ ? "\n" : ""), substr($$0, 5); next} \
			{printf "  %s%-18s%s %s\n", on, $$1, off, $$2}'

install: $(STAMP) ## Create .venv and install the package (CPU torch first); idempotent

$(STAMP): pyproject.toml
	@test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q "$(TORCH_SPEC)"
	$(BIN)/pip install -q -e '.[dev]'
	@touch $(STAMP)

# The default tier on every core (at most 4 workers; each test file stays on one worker, so a
# file's fixtures are built once): about half the serial time on 2 cores (docs/performance_log.md).
# PYTEST_WORKERS=0 runs it serially, in one process.
PYTEST_WORKERS ?= auto
test: install ## Run the default (fast) test tier, on every core (PYTEST_WORKERS=0: serially)
	$(BIN)/python -m pytest -q -n $(PYTEST_WORKERS) --maxprocesses=4 --dist loadfile

test-slow: install ## Run the slow tier (end-to-end runs, sweeps, DDP)
	$(BIN)/python -m pytest -q -m slow

lint: install ## ruff check + format check
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

format: install ## Apply ruff formatting and safe fixes
	$(BIN)/ruff check --fix .
	$(BIN)/ruff format .

##@ The paper's pipeline (SCALE=tiny|demo|paper, ARGS=<Hydra overrides>)

demo: install ## The whole paper pipeline at demo scale on the synthetic surveys, then the report
	$(BIN)/python -m sss2bathy.cli.pipeline scale=$(SCALE) $(ARGS)

paper: install ## Every experiment at scale=paper (GPU), then the report
	$(BIN)/python -m sss2bathy.cli.pipeline scale=paper $(ARGS)

prepare: install ## Generate + drape the synthetic surveys (cached)
	$(BIN)/sss2bathy-prepare data/survey=synthetic_d1 scale=$(SCALE) $(ARGS)
	$(BIN)/sss2bathy-prepare data/survey=synthetic_d2 scale=$(SCALE) $(ARGS)
	$(BIN)/sss2bathy-prepare data/survey=synthetic_d3 scale=$(SCALE) $(ARGS)

# The paper's experiments, one make target each. conf/experiment/<name>.yaml's `pipeline` key
# names an experiment's target; the pipeline runs the target's experiments, training a CNN
# first when one reads a CNN and no run of this scale has one.
EXPERIMENT_TARGETS := $(sort $(shell sed -n 's/^  make: *//p' conf/experiment/*.yaml 2>/dev/null))
.PHONY: $(EXPERIMENT_TARGETS)
$(EXPERIMENT_TARGETS): install
	$(BIN)/python -m sss2bathy.cli.pipeline scale=$(SCALE) make=$@ $(ARGS)
cnn: ## Paper experiment: normal CNN (train d1; test d1 test lines, d2, d3, site2)
siren-direct-fit: ## Paper experiment: SIREN fitted to the MBES grid directly
siren-heights-only: ## Ablation: SIREN from the altimeter heights alone (what the sidescan must beat)
siren-gt-n2d: ## Paper experiment: SIREN from draped MBES normals + altimeter
siren-cnn-n2d: ## Paper experiment: SIREN from CNN normals + altimeter (trains a CNN if none)
siren-cnn-n2d-pretrained: ## SIREN from the shipped pretrained CNN's normals + altimeter (no CNN training)
siren-lambert-all: ## Paper experiment: Lambertian baseline, all lines of sidescan
siren-lambert: ## Paper experiment: Lambertian baseline, 12 test lines
d2: ## Paper experiment: Dataset-II analogue (CNN-N2d with the demo's and the shipped CNN, and Lambert on synthetic_d2)
d3: ## Stress site: another sonar (CNN-N2d with the demo's and the shipped CNN, and Lambert on synthetic_d3)

report: install ## Gather the latest run of each experiment into outputs/report/
	$(BIN)/sss2bathy-report $(ARGS)

results: install ## The report, then its tables into docs/results.md and the README's results (after make demo)
	$(BIN)/sss2bathy-report --publish $(ARGS)

##@ Your own survey

map: install ## Your own survey: XTF=<files/folder/glob> [CKPT=<cnn ckpt>] -> map.tif, map.png, metrics.json
	@test -n "$(XTF)" || { echo "make map: expected XTF=<folder, file or glob of .xtf files>, found none"; exit 2; }
	$(BIN)/python -m sss2bathy.cli.map 'files=$(XTF)' scale=$(SCALE) $(if $(CKPT),'cnn_checkpoint=$(CKPT)') $(ARGS)

##@ Sweeps

sweep-example: install ## A small Hydra multirun sweep (w_H x seed) on SIREN-GT-N2d
	$(BIN)/sss2bathy-train -m experiment=siren_gt_n2d scale=$(SCALE) model.w_height=0.1,1,10 seed=1,2 $(ARGS)

EXPERIMENT ?= siren_lambert
sweep-siren: install ## Optuna search of a SIREN fit (w_H, lr, omega0, lr decay) on the held-out altimeter MAE, no MBES needed [EXPERIMENT=siren_lambert]
	$(BIN)/sss2bathy-train -m experiment=$(EXPERIMENT) hparams_search=siren_optuna scale=$(SCALE) $(ARGS)

##@ Studies (tables and figures under outputs/)

.PHONY: xtf-study
xtf-study: install ## Generated AUV XTF surveys without MBES: held-out altimeter vs interpolation, 3 seeds, one fit at a time [CKPT=<cnn ckpt>] -> outputs/xtf_study/
	OMP_NUM_THREADS=1 $(BIN)/python -m studies.xtf_study --scale $(SCALE) --out outputs/xtf_study $(if $(CKPT),--cnn-checkpoint '$(CKPT)') $(ARGS)

# a CNN of this scale for the studies that read one: trained only if none exists
CNN_IF_NONE = $(BIN)/python -m sss2bathy.cli.pipeline scale=$(SCALE) needs=[cnn] $(ARGS)
STUDY := outputs/study/$(SCALE)
STUDY_TRAIN := $(BIN)/sss2bathy-train experiment=siren_cnn_n2d scale=$(SCALE) model.log_images=false
schedule-study: install ## SIREN-CNN-N2d: paper schedule vs fast schedule, map MAE over time (paper run: hours on a CPU)
	$(CNN_IF_NONE)
	$(STUDY_TRAIN) siren_schedule=fast scale.siren.eval_every_n_epochs=1 hydra.run.dir=$(STUDY)/fast $(ARGS)
	$(STUDY_TRAIN) scale.siren.eval_every_n_epochs=1 hydra.run.dir=$(STUDY)/scale_default $(ARGS)
	$(STUDY_TRAIN) siren_schedule=paper scale.siren.eval_every_n_epochs=25 hydra.run.dir=$(STUDY)/paper $(ARGS)
	$(BIN)/python -m studies.schedule_study --reference paper --reference-epochs 1500 \
		--run paper=$(STUDY)/paper --run fast=$(STUDY)/fast --run $(SCALE)=$(STUDY)/scale_default --out $(STUDY)

.PHONY: lambert-tune
TUNE := outputs/multiruns/lambert_tune/$(SCALE)
TUNE_TRAIN := $(BIN)/sss2bathy-train -m experiment=lambert_tune scale=$(SCALE) torch_threads=1
lambert-tune: install ## SIREN-Lambert settings sweep on d1 TRAINING lines, one run at a time (13 runs, ~15 min) -> outputs/lambert_tune/
	rm -rf $(TUNE)
	$(TUNE_TRAIN) model.sensor.q=1,2,4 model.sensor.reflectivity=constant,field hydra.sweep.dir=$(TUNE)/q_reflectivity $(ARGS)
	$(TUNE_TRAIN) model.sensor.q=6 model.sensor.reflectivity=field hydra.sweep.dir=$(TUNE)/q_edge $(ARGS)
	$(TUNE_TRAIN) model.sensor.shadow_threshold=0,0.5 hydra.sweep.dir=$(TUNE)/shadow_threshold $(ARGS)
	$(TUNE_TRAIN) model.sensor.near_range_cut_m=16 hydra.sweep.dir=$(TUNE)/near_range_cut $(ARGS)
	$(TUNE_TRAIN) model.sensor.reflectivity=field model.sensor.field_lr=1e-2 hydra.sweep.dir=$(TUNE)/field_lr $(ARGS)
	$(TUNE_TRAIN) model.sensor.reflectivity=field model.sensor.field_weight=0,0.1 hydra.sweep.dir=$(TUNE)/field_weight $(ARGS)
	$(BIN)/python -m studies.lambert_tune $(TUNE) --out outputs/lambert_tune/$(SCALE)

.PHONY: wreck-study
wreck-study: install ## Do the maps show wrecks? Lambert, CNN-N2d (the shipped CNN), GT-N2d, heights-only on a simulated survey with five objects, with map_settings=scale, survey (one finer SIREN + occlusion term) and detail (the default: scale + a detail network), one fit at a time (~35 min demo) -> outputs/wreck_study/
	OMP_NUM_THREADS=1 $(BIN)/python -m studies.wreck_study --scale $(SCALE) --out outputs/wreck_study/$(SCALE) $(ARGS)

.PHONY: valsite-study
VALSITE := outputs/valsite_study/$(SCALE)
VALSITE_TRAIN := $(BIN)/sss2bathy-train data/survey=synthetic_d1_valsite scale=$(SCALE) torch_threads=1 model.log_images=false
VALSITE_OLD_LR := scale.siren.lr=3.0e-3 scale.siren.gamma=0.8
valsite-study: install ## SIREN settings on the validation site (d1's recipe, seed 7; not a test set): GT-N2d, CNN-N2d, Lambert at the scale's lr and 3e-3, CNN-N2d with line offsets; one fit at a time (~9 min demo) -> outputs/valsite_study/
	$(CNN_IF_NONE)
	rm -rf $(VALSITE)
	for e in gt_n2d cnn_n2d lambert; do \
		$(VALSITE_TRAIN) experiment=siren_$$e hydra.run.dir=$(VALSITE)/$${e}_scale_lr $(ARGS) || exit 1; \
		$(VALSITE_TRAIN) experiment=siren_$$e $(VALSITE_OLD_LR) hydra.run.dir=$(VALSITE)/$${e}_lr3e-3 $(ARGS) || exit 1; \
	done
	$(VALSITE_TRAIN) experiment=siren_cnn_n2d model.line_offset=true hydra.run.dir=$(VALSITE)/cnn_n2d_line_offset $(ARGS)
	$(VALSITE_TRAIN) experiment=siren_cnn_n2d model.line_offset=true $(VALSITE_OLD_LR) \
		hydra.run.dir=$(VALSITE)/cnn_n2d_line_offset_lr3e-3 $(ARGS)
	$(BIN)/python -m studies.valsite_study $(VALSITE)

.PHONY: valsite-w-height
WH_WEIGHTS ?= 0.003 0.01 0.03 0.1 0.3 1 3
VALSITE_SEEDS ?= 42 43 44
valsite-w-height: install ## The altimeter weight per sensor on the validation site: GT-N2d, CNN-N2d (demo and shipped CNN), Lambert at WH_WEIGHTS x VALSITE_SEEDS, one fit at a time (~90 min demo) -> outputs/valsite_w_height/
	$(CNN_IF_NONE)
	for e in gt_n2d cnn_n2d cnn_n2d_pretrained lambert; do for w in $(WH_WEIGHTS); do for s in $(VALSITE_SEEDS); do \
		d=outputs/valsite_w_height/$(SCALE)/$${e}_wh$${w}_s$${s}; [ -f $$d/metrics.json ] && continue; \
		$(VALSITE_TRAIN) experiment=siren_$$e model.w_height=$$w seed=$$s logger=none hydra.run.dir=$$d $(ARGS) || exit 1; \
	done; done; done
	$(BIN)/python -m studies.valsite_study outputs/valsite_w_height/$(SCALE)

.PHONY: valsite-seabeds
SEABEDS_N ?= 1 2 4 8
valsite-seabeds: install ## The demo CNN on SEABEDS_N seabeds of d1's kind (experiment=cnn_seabeds, 20 epochs each), judged by the validation site's map over VALSITE_SEEDS, one job at a time (~2 h demo) -> outputs/valsite_seabeds/
	for n in $(SEABEDS_N); do \
		list='$${data.survey}'; i=1; for k in b c d e f g h; do [ $$i -lt $$n ] || break; \
			list="$$list,\$${d1_seabeds.$$k}"; i=$$((i+1)); done; \
		c=outputs/runs/cnn_seabeds/$(SCALE)/seabeds$$n; \
		[ -f $$c/checkpoints/last.ckpt ] || $(BIN)/sss2bathy-train experiment=cnn_seabeds scale=$(SCALE) \
			torch_threads=1 test=false callbacks.model_checkpoint.save_last=true \
			"data.train_surveys=[$$list]" hydra.run.dir=$$c $(ARGS) || exit 1; \
		for s in $(VALSITE_SEEDS); do d=outputs/valsite_seabeds/$(SCALE)/seabeds$${n}_s$$s; \
			[ -f $$d/metrics.json ] && continue; \
			$(VALSITE_TRAIN) experiment=siren_cnn_n2d seed=$$s data.normals.checkpoint=$$c/checkpoints/last.ckpt \
				logger=none hydra.run.dir=$$d || exit 1; \
		done; \
	done
	$(BIN)/python -m studies.valsite_study outputs/valsite_seabeds/$(SCALE)

LC_N_TRAIN ?= 8,16,32
.PHONY: learning-curve
learning-curve: install ## CNN test MAE vs training lines / time, one survey, fixed test lines -> outputs/learning_curve/
	$(BIN)/python -m studies.learning_curve --n-train $(LC_N_TRAIN) --scale $(SCALE) \
		--torch-threads $${TORCH_THREADS:-1} --out outputs/learning_curve $(ARGS)

.PHONY: real1m-figure real1m
real1m-figure: install ## The synthetic_real_1m survey (real 1 m MBES grid as terrain) + hillshade/waterfall figure -> outputs/figures/synthetic_real_1m.png
	$(BIN)/sss2bathy-prepare data/survey=synthetic_real_1m scale=$(SCALE) $(ARGS)
	$(BIN)/python -m studies.real_figure data/synthetic_real_1m_$(SCALE) outputs/figures/synthetic_real_1m.png

real1m: install ## The real 1 m grid survey: SIREN GT-N2d, CNN-N2d, Lambert, heights-only, one fit at a time (CNN-N2d needs a CNN run)
	for e in gt_n2d cnn_n2d lambert heights_only; do \
		$(BIN)/sss2bathy-train experiment=real1m_siren_$$e scale=$(SCALE) torch_threads=1 $(ARGS) || exit 1; \
	done

.PHONY: paper-cpu-study
BUDGET ?= 20
paper-cpu-study: install ## Paper-scale d1 on a CPU: prepared once, SIREN-GT-N2d and Lambert at the paper and budget schedules, BUDGET min each -> outputs/paper_cpu_study/
	$(BIN)/python -m studies.paper_cpu_study --scale paper --budget-min $(BUDGET) $(ARGS)

.PHONY: scaling-study
scaling-study: install ## Cost vs survey size: XTF import, draping, CNN inference, SIREN fit at 1x/4x/16x the demo survey, one thread; exponents + figure (~35 min on a busy 2-core CPU) -> outputs/scaling_study/
	$(BIN)/python -m studies.scaling_study --out outputs/scaling_study $(ARGS)
	$(BIN)/python -m studies.scaling_study --long-line --sizes-mb 50 500 --out outputs/scaling_study

.PHONY: tile-seams
tile-seams: install ## Tiled vs single SIREN-Lambert map of a generated XTF survey: seam steps and MAE against the MBES, one fit at a time -> outputs/tile_seams/
	$(BIN)/python -m studies.tile_seams --out outputs/tile_seams $(ARGS)

##@ Models

.PHONY: pretrain
pretrain: install ## The pretrained normal CNN on twelve simulated seabeds (six recipes) with randomised sonars -> outputs/runs/pretrain/ (SCALE=demo: the seabeds prepared once, then ~75 min of training on 2 CPU cores; SCALE=paper ARGS=trainer=gpu)
	$(BIN)/sss2bathy-train experiment=pretrain scale=$(SCALE) torch_threads=$${TORCH_THREADS:-1} data.prepare_jobs=$$(nproc) $(ARGS)

# the shipped model's recipe (docs/pretrained_model.md): 32 lines on each of the twelve
# seabeds, width 16 x 6 blocks, 17-epoch lr schedule stopped after 7573 steps (the shipped run
# was stopped there by a 4-min limit on an H200); the best validation epoch is the model
PRETRAIN_GPU := scale=demo scale.survey.synthetic_pretrain.plan.n_train=32 trainer=gpu \
	trainer.precision=bf16-mixed model.channels_last=true data.num_workers=10 data.pin_memory=true \
	scale.pretrain.base_width=16 scale.pretrain.n_blocks=6 scale.pretrain.batch_size=32 \
	scale.pretrain.lr=5.0e-4 scale.pretrain.overlap=0.75 scale.pretrain.overlap_bins=0.5 \
	scale.pretrain.max_epochs=17 scale.pretrain.max_steps=7573 test=false 'data.test_surveys=[]' \
	data.prepare_jobs=$$(nproc)
.PHONY: pretrain-gpu
pretrain-gpu: install ## The shipped pretrained CNN's recipe on a GPU (the twelve seabeds prepared once, side by side: 2 min on 16 cores; then ~4 min of training on an H200) -> outputs/runs/pretrain/
	$(BIN)/sss2bathy-train experiment=pretrain $(PRETRAIN_GPU) $(ARGS)

##@ Benchmarks and tools

bench: install ## Benchmarks -> outputs/bench/ (JSON + Markdown)
	$(BIN)/python -m benchmarks $(ARGS)

.PHONY: thread-bench
thread-bench: install ## Thread policies under load: demo CNN and SIREN steps, 2 threads spinning / passive / 1 thread, quiet and beside a nice-19 busy loop -> outputs/thread_policy/
	$(BIN)/python -m benchmarks.thread_policy $(ARGS)

.PHONY: gpu-check
gpu-check: install ## On a CUDA GPU (<= 10 min): paper-scale SIREN-GT-N2d to within 10 % of its best map, one paper-width CNN epoch, the GPU's name and memory -> outputs/gpu_check/ (no GPU: one line, exit 0)
	$(BIN)/python -m studies.gpu_check $(ARGS)

tb: install ## TensorBoard on outputs/
	$(BIN)/tensorboard --logdir outputs/ --bind_all

clean: ## Remove caches and outputs (keeps data/ and .venv)
	rm -rf outputs/runs outputs/multiruns outputs/report outputs/bench .pytest_cache .ruff_cache
	find . -name __pycache__ -type d -prune -exec rm -rf {} +
